"""A user-space TCP proxy that adds a fixed one-way delay in each direction.

For links without ``tc netem`` (e.g. between network namespaces on a kernel built without it):
every connection accepted on ``--listen`` is relayed to ``--target``, and each chunk of bytes,
in either direction, is forwarded ``--delay-ms`` after it arrived. Throughput is not limited:
per direction one task reads as data arrives and stamps each chunk with its arrival time, and
another writes each chunk when its stamp + delay is due, so many chunks are in flight at once
(the delay line holds up to ``max_buffer`` bytes per direction before reading pauses). Both
sockets have ``TCP_NODELAY`` (no Nagle delay on top of ours). A half close (EOF) is delayed
like data; a reset or error on one side closes both.

Library::

    proxy = DelayProxy(listen=("127.0.0.1", 0), target=("127.0.0.1", 7447), delay_ms=20)
    proxy.start()            # an event loop in a thread; returns once it listens
    port = proxy.port        # the port bound (useful with port 0)
    ...
    proxy.stop()             # closes the listener and every relayed connection

CLI (e.g. inside a network namespace, with ``ip netns exec``)::

    python tools/delay_proxy.py --listen 10.1.0.1:7448 --target 10.1.0.1:7447 --delay-ms 20

prints ``delay_proxy: listening on ADDR:PORT`` once it listens, and runs until SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import signal
import socket
import sys
import threading

CHUNK = 256 * 1024
#: Bytes a direction may hold in its delay line before its reader pauses.
MAX_BUFFER = 64 * 1024 * 1024


def _nodelay(writer: asyncio.StreamWriter) -> None:
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class _Direction:
    """One direction of one connection: a reader that stamps, a writer that waits."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        delay: float,
        max_buffer: int,
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.delay = delay
        self.max_buffer = max_buffer
        self.line: collections.deque[tuple[float, bytes]] = collections.deque()
        self.buffered = 0
        self.arrived = asyncio.Event()  # something entered the line
        self.room = asyncio.Event()  # the line has room again
        self.room.set()

    async def read(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await self.room.wait()
            data = await self.reader.read(CHUNK)
            self.line.append((loop.time() + self.delay, data))
            self.arrived.set()
            if not data:  # EOF: delayed like data
                return
            self.buffered += len(data)
            if self.buffered >= self.max_buffer:
                self.room.clear()

    async def write(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            while not self.line:
                self.arrived.clear()
                await self.arrived.wait()
            due, data = self.line[0]
            wait = due - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            self.line.popleft()
            if not data:
                with contextlib.suppress(OSError):
                    if self.writer.can_write_eof():
                        self.writer.write_eof()
                return
            self.writer.write(data)
            self.buffered -= len(data)
            if self.buffered < self.max_buffer:
                self.room.set()
            await self.writer.drain()


class DelayProxy:
    """A TCP proxy from ``listen`` to ``target`` with ``delay_ms`` each way."""

    def __init__(
        self,
        listen: tuple[str, int],
        target: tuple[str, int],
        delay_ms: float,
        *,
        max_buffer: int = MAX_BUFFER,
    ) -> None:
        if delay_ms < 0:
            raise ValueError("delay_ms must be >= 0")
        self.listen = listen
        self.target = target
        self.delay = delay_ms / 1000.0
        self.max_buffer = max_buffer
        self.port: int | None = None
        #: Connections accepted so far.
        self.accepted = 0
        self._server: asyncio.base_events.Server | None = None
        self._conns: set[asyncio.Task] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._stopped: asyncio.Event | None = None

    # ---- asyncio API -------------------------------------------------------------------
    async def open(self) -> None:
        """Start listening (in the running loop)."""
        self._stopped = asyncio.Event()
        self._server = await asyncio.start_server(
            self._accept, self.listen[0], self.listen[1], reuse_address=True
        )
        self.port = self._server.sockets[0].getsockname()[1]

    async def close(self) -> None:
        """Stop listening and drop every relayed connection."""
        if self._server is not None:
            self._server.close()
        for task in list(self._conns):
            task.cancel()
        if self._conns:
            await asyncio.gather(*self._conns, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
        if self._stopped is not None:
            self._stopped.set()

    async def serve(self) -> None:
        """Listen and relay until `close` (or the task is cancelled)."""
        if self._server is None:
            await self.open()
        assert self._stopped is not None
        await self._stopped.wait()

    async def _accept(self, c_reader: asyncio.StreamReader, c_writer: asyncio.StreamWriter):
        task = asyncio.current_task()
        assert task is not None
        self._conns.add(task)
        self.accepted += 1
        t_writer = None
        try:
            _nodelay(c_writer)
            try:
                t_reader, t_writer = await asyncio.open_connection(*self.target)
            except OSError:
                return
            _nodelay(t_writer)
            up = _Direction(c_reader, t_writer, self.delay, self.max_buffer)
            down = _Direction(t_reader, c_writer, self.delay, self.max_buffer)
            tasks = [asyncio.ensure_future(c) for c in (up.read(), up.write(), down.read(),
                                                        down.write())]  # fmt: skip
            try:
                # Each direction ends by relaying its EOF; an error anywhere ends both.
                pending = set(tasks)
                while pending:
                    done, pending = await asyncio.wait(pending, return_when=asyncio.FIRST_COMPLETED)
                    if any(t.exception() for t in done if not t.cancelled()):
                        break
            finally:
                for t in tasks:
                    t.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
        except asyncio.CancelledError:
            pass  # the proxy is closing (returning keeps asyncio's server from logging it)
        finally:
            for w in (c_writer, t_writer):
                if w is not None:
                    w.close()
                    with contextlib.suppress(Exception):
                        await w.wait_closed()
            self._conns.discard(task)

    # ---- thread API --------------------------------------------------------------------
    def start(self, timeout: float = 5.0) -> DelayProxy:
        """Run the proxy on an event loop in a daemon thread; return once it listens."""
        ready = threading.Event()
        error: list[BaseException] = []

        def main() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            try:
                try:
                    loop.run_until_complete(self.open())
                except BaseException as e:
                    error.append(e)
                    return
                finally:
                    ready.set()
                loop.run_until_complete(self.serve())
            finally:
                loop.close()

        self._thread = threading.Thread(target=main, name="delay-proxy", daemon=True)
        self._thread.start()
        if not ready.wait(timeout):
            raise TimeoutError("the delay proxy did not start")
        if error:
            raise error[0]
        return self

    def stop(self, timeout: float = 5.0) -> None:
        if self._loop is None or self._thread is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop already ended
            asyncio.run_coroutine_threadsafe(self.close(), self._loop).result(timeout)
        self._thread.join(timeout)
        self._thread = None

    def __enter__(self) -> DelayProxy:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()


def _endpoint(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected ADDR:PORT, got {text!r}")
    return host.strip("[]") or "0.0.0.0", int(port)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--listen", type=_endpoint, required=True, metavar="ADDR:PORT")
    p.add_argument("--target", type=_endpoint, required=True, metavar="ADDR:PORT")
    p.add_argument("--delay-ms", type=float, required=True, help="one-way delay, each direction")
    args = p.parse_args(argv)
    proxy = DelayProxy(args.listen, args.target, args.delay_ms)

    async def run() -> None:
        await proxy.open()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, lambda: asyncio.ensure_future(proxy.close()))
        print(
            f"delay_proxy: listening on {args.listen[0]}:{proxy.port} -> "
            f"{args.target[0]}:{args.target[1]}, {args.delay_ms:g} ms each way",
            flush=True,
        )
        await proxy.serve()

    asyncio.run(run())
    return 0


if __name__ == "__main__":
    sys.exit(main())
