"""A cuttable TCP link: what a scenario puts between two hosts' routers to pull the cable.

`Link` relays every connection accepted on ``127.0.0.1:<free port>`` to a target (the first
host's router). `Link.cut` makes it behave like a pulled cable: nothing is forwarded in
either direction any more, no FIN or RST reaches either end (each end finds out only by its
own timeout: for Zenoh, the transport lease), and new connections are accepted and then held
in silence. `Link.restore` closes every connection it relays or holds (both ends have given
them up by then) and forwards new ones again, so the ends reconnect as they would after a
real outage. While the target does not listen yet, a new connection is held and dialled again
every `REDIAL` seconds (the hosts may start before the router they join).

The relay is an asyncio loop in a daemon thread; `cut`, `restore` and `close` are called from
any thread and return once they are in effect::

    link = Link(("127.0.0.1", 7447))
    link.start()                 # listening once it returns
    link.endpoint                # "tcp/127.0.0.1:<port>": what the other host connects to
    link.cut(); link.restore(); link.close()
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
from collections.abc import Coroutine
from typing import Any

CHUNK = 64 * 1024
#: Seconds between two attempts to reach a target that does not listen (yet).
REDIAL = 0.05


class Link:
    """A TCP relay from ``listen`` to ``target`` that can be cut and restored."""

    def __init__(self, target: tuple[str, int], listen: tuple[str, int] = ("127.0.0.1", 0)) -> None:
        self.target = target
        self.listen = listen
        self.port = 0
        self._cut = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.Server | None = None
        self._thread: threading.Thread | None = None
        #: Every socket of a connection relayed or held (client and target sides).
        self._writers: set[asyncio.StreamWriter] = set()
        #: The tasks forwarding (or dialling for) a connection.
        self._tasks: set[asyncio.Task[Any]] = set()

    # ---- the thread-safe interface -------------------------------------------------------
    @property
    def endpoint(self) -> str:
        """The Zenoh endpoint of the link's near end."""
        return f"tcp/{self.listen[0]}:{self.port}"

    @property
    def is_cut(self) -> bool:
        return self._cut

    def start(self) -> None:
        """Listen and relay, in a thread of its own; returns once listening."""
        ready = threading.Event()
        failed: list[BaseException] = []

        def main() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            try:
                loop.run_until_complete(self._listen())
            except BaseException as e:  # reported to start()
                failed.append(e)
                ready.set()
                loop.close()
                return
            ready.set()
            loop.run_forever()
            loop.close()

        self._thread = threading.Thread(target=main, name=f"link-{self.target[1]}", daemon=True)
        self._thread.start()
        ready.wait()
        if failed:
            raise failed[0]

    def cut(self) -> None:
        """Pull the cable: forward nothing, close nothing, hold new connections."""
        self._call(self._do_cut())

    def restore(self) -> None:
        """Plug it back: close every connection (dead at both ends by now), forward again."""
        self._call(self._do_restore())

    def close(self) -> None:
        """Stop listening and close every connection; the thread ends."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        self._call(self._do_close())
        loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(5.0)
        self._loop = None

    def _call(self, coro: Coroutine[Any, Any, None]) -> None:
        if self._loop is None:
            coro.close()
            raise RuntimeError("the link is not started")
        asyncio.run_coroutine_threadsafe(coro, self._loop).result(5.0)

    # ---- the loop ------------------------------------------------------------------------
    async def _listen(self) -> None:
        self._server = await asyncio.start_server(self._accept, *self.listen)
        self.port = self._server.sockets[0].getsockname()[1]

    async def _do_cut(self) -> None:
        self._cut = True
        for task in list(self._tasks):  # their sockets stay open: no FIN, no RST
            task.cancel()

    async def _do_restore(self) -> None:
        await self._do_cut()
        self._abort_all()
        self._cut = False

    async def _do_close(self) -> None:
        await self._do_cut()
        if self._server is not None:
            self._server.close()
        self._abort_all()

    def _abort_all(self) -> None:
        for writer in list(self._writers):
            writer.transport.abort()
        self._writers.clear()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        if self._cut:
            return  # held in silence until restore() closes it
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            await self._relay(reader, writer)
        except asyncio.CancelledError:
            pass  # cut: leave both sockets as they are
        finally:
            self._tasks.discard(task)

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await self._dial()
        self._writers.add(up_writer)
        for w in (writer, up_writer):
            _nodelay(w)
        try:
            async with asyncio.TaskGroup() as pumps:
                pumps.create_task(_pump(reader, up_writer))
                pumps.create_task(_pump(up_reader, writer))
        except* OSError:  # a reset on one side: reset the other, as its router would see it
            for w in (writer, up_writer):
                w.transport.abort()
        else:  # both sides closed in order (each half close was forwarded)
            for w in (writer, up_writer):
                w.close()
        for w in (writer, up_writer):
            self._writers.discard(w)

    async def _dial(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        while True:
            try:
                return await asyncio.open_connection(*self.target)
            except OSError:
                await asyncio.sleep(REDIAL)


async def _pump(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    """Forward ``src`` to ``dst`` until EOF, then half-close ``dst``."""
    while data := await src.read(CHUNK):
        dst.write(data)
        await dst.drain()
    if dst.can_write_eof():
        dst.write_eof()


def _nodelay(writer: asyncio.StreamWriter) -> None:
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
