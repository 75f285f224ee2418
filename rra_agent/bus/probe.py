"""Why a hub does not link with a tool's Zenoh session: quick, definite answers.

Zenoh keeps dialling an endpoint that accepts TCP connections until its connect timeout
(10 s by default): a TLS client at a hub without TLS (the hub waits for a Zenoh frame that
never comes), a client without TLS at a TLS hub, a TLS client of another system's CA all
look to it like a hub slow to answer. `diagnose` asks the questions Zenoh does not, each in a
fraction of a second: does the endpoint answer a TLS handshake, with a certificate of the
CA of ``--certs``, naming the address dialled? does a plain Zenoh session link there? A tool
(`rra_agent.bus.client.open_tool_session`) asks once its session has not linked within
`AFTER`, fails at once on a definite answer, and otherwise waits on for Zenoh: a slow hub
(a loaded machine) is never refused for being slow.
"""

from __future__ import annotations

import contextlib
import queue
import socket
import ssl
import threading
import time
from collections.abc import Callable
from typing import Any

from rra_agent.bus.config import BusConfig, Tls, split_endpoint

#: How long a tool's first try to link may take before `diagnose` looks (a local hub links
#: in 5-20 ms; a slower one is tried again once the probes found nothing definite).
AFTER = 0.15
#: How long a TLS handshake may take to be answered (a hub without TLS never answers: a
#: plain session is tried beside it, and links in a few ms).
TLS_TIMEOUT = 0.5
#: How long an alert refusing the client's certificate may take after the handshake (TLS 1.3
#: sends it after the client has finished).
ALERT_TIMEOUT = 0.05
#: How long a ``tcp/`` endpoint may leave a TLS handshake unanswered before it is taken for
#: no TLS hub (a hub without TLS, the one expected, never answers it: this is what a slow
#: hub costs a tool before it tries again).
TLS_ANSWER = 0.25
#: How long a TLS handshake may stay unanswered before a plain Zenoh session is tried too.
SILENT_AFTER = 0.05
#: How long a plain Zenoh session may take to link to a hub that has no TLS.
PLAIN_TIMEOUT = 0.5


def diagnose(bus: BusConfig) -> str | None:
    """Why no session links at ``bus``'s connect endpoints, when that is certain (one line),
    else None."""
    for ep in bus.connect:
        proto, host, port = split_endpoint(ep)
        if not port.isdigit() or host in ("", "0.0.0.0", "::"):
            continue
        if proto == "tcp":
            why = _tls_at_plain(ep, host, int(port))
        elif proto == "tls" and bus.tls is not None:
            why = _tls_refused(ep, host, int(port), bus.tls)
        else:
            why = None
        if why is not None:
            return why
    return None


def _handshake(
    host: str, port: int, context: ssl.SSLContext, timeout: float = 0.0
) -> ssl.SSLSocket:
    """A TLS connection to ``host:port`` (``timeout``, default `TLS_TIMEOUT`, for the
    connection and the handshake)."""
    raw = socket.create_connection((host, port), timeout=timeout or TLS_TIMEOUT)
    try:
        return context.wrap_socket(raw, server_hostname=host)
    except BaseException:
        raw.close()
        raise


def _tls_at_plain(ep: str, host: str, port: int) -> str | None:
    """A ``tcp/`` endpoint where a TLS server answers: a TLS hub."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    try:
        with _handshake(host, port, context, TLS_ANSWER):
            pass
    except (OSError, ssl.SSLError):
        return None  # no TLS server (a plain Zenoh hub waits for a frame: a timeout)
    return (
        f"{ep} is a TLS hub (certificates): give --certs DIR/operator (from `rra certs`) and "
        f"--connect tls/{host}:{port}"
    )


def _tls_refused(ep: str, host: str, port: int, tls: Tls) -> str | None:
    """A ``tls/`` endpoint: a certificate of another CA, or not naming ``host``; a hub that
    refuses this certificate; something else than a TLS server; a hub without TLS (a plain
    Zenoh session links there: tried beside the handshake, which such a hub never answers)."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    try:
        context.load_verify_locations(tls.ca)
        context.load_cert_chain(tls.cert, tls.key)
    except (OSError, ssl.SSLError):
        return None  # the files: `no_system` names the one that is wrong
    answers: queue.Queue[tuple[str, str | None]] = queue.Queue()
    _ask(answers, "tls", _tls_verdict, ep, host, port, tls, context)
    # A TLS hub answers at once: only a silent one is tried without TLS (every connection
    # a Zenoh TLS listener drops delays its next accept by ~0.1 s).
    try:
        _, answer = answers.get(timeout=SILENT_AFTER)
        if answer != _SILENT:
            return answer
    except queue.Empty:
        pass
    _ask(answers, "plain", _plain_hub, ep, host, port)
    deadline = time.monotonic() + TLS_TIMEOUT + PLAIN_TIMEOUT
    for _ in range(2):
        try:
            who, answer = answers.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            break
        if answer is not None and answer != _SILENT:
            return answer
        if who == "tls" and answer is None:
            return None  # a TLS hub that accepts this certificate
    return None


def _ask(answers: queue.Queue[tuple[str, str | None]], who: str, fn: Callable[..., str | None],
         *args: Any) -> None:  # fmt: skip
    """Run ``fn(*args)`` in a daemon thread (never waited for at exit), its answer queued."""

    def run() -> None:
        try:
            answers.put((who, fn(*args)))
        except Exception:
            answers.put((who, None))

    threading.Thread(target=run, name=f"probe-{who}", daemon=True).start()


#: `_tls_verdict`: no answer to the handshake (a plain Zenoh hub waits for a frame).
_SILENT = "silent"


def _tls_verdict(ep: str, host: str, port: int, tls: Tls, context: ssl.SSLContext) -> str | None:
    try:
        conn = _handshake(host, port, context)
    except ssl.SSLCertVerificationError as e:
        return _not_ours(ep, host, tls, e)
    except TimeoutError:
        return _SILENT
    except ConnectionRefusedError:
        return None  # nothing listens: the caller says so
    except (ssl.SSLError, ConnectionError) as e:
        return f"something listens at {ep} but it is no TLS hub ({_reason(e)})"
    except OSError:
        return None
    with conn:
        return _refused_after(ep, conn)


def _not_ours(ep: str, host: str, tls: Tls, e: ssl.SSLCertVerificationError) -> str:
    if "mismatch" in (e.verify_message or ""):
        return (
            f"the hub at {ep} has a certificate that does not name {host}: make the "
            f"certificates with `rra certs PKG --san HOST={host}` (the address dialled)"
        )
    return (
        f"something listens at {ep} but no Zenoh session opens: the TLS handshake was refused: "
        f"the hub's certificate is not signed by the CA of --certs ({tls.ca}): are the "
        "certificates of --certs from this system's `rra certs`?"
    )


def _refused_after(ep: str, conn: ssl.SSLSocket) -> str | None:
    """The hub's alert refusing this client's certificate, if it sends one at once."""
    conn.settimeout(ALERT_TIMEOUT)
    try:
        conn.recv(1)
    except ssl.SSLError as e:
        return f"the hub at {ep} refused the certificate of --certs ({_reason(e)})"
    except OSError:
        pass  # nothing within the timeout: the hub waits for Zenoh's first message
    return None


def _plain_hub(ep: str, host: str, port: int) -> str | None:
    """No answer to a TLS handshake: a Zenoh hub without TLS, if a plain session links."""
    from rra_agent.bus.session import NoPeer, open_session

    plain = f"tcp/{host}:{port}"
    bus = BusConfig(connect=[plain], multicast=False, connect_timeout_ms=int(PLAIN_TIMEOUT * 1e3))
    try:
        session = open_session(bus, wait_connected=True)
    except (NoPeer, Exception):
        return None
    with contextlib.suppress(Exception):
        session.close()
    return f"{ep} is a hub without TLS: connect with --connect {plain}"


def _reason(e: BaseException) -> str:
    return str(getattr(e, "reason", None) or e).lower().replace("_", " ")
