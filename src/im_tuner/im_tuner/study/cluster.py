"""``study --cluster``: the scheduler's address checked, and the scheduler itself checked
before any work, each within a bounded time.

* :func:`check_address` (no network, no Dask import): ``tcp://HOST:PORT`` with a host
  name or IP address and a port in 1..65535.  ``tls://`` is refused: Dask's TLS needs
  certificates on both sides, which the study does not take (a tunnel, ``ssh -L``, gives
  an encrypted link to a ``tcp://`` scheduler).
* :func:`wait_for_scheduler`: a plain TCP connection first (nothing listening: refused
  at once), then Dask's handshake and the scheduler's ``identity`` call, each bounded by
  ``timeout`` s.  Dask's own ``Client(address, timeout=...)`` bounds only the TCP
  connection: a server that accepts and never answers holds it for ever, one that answers
  with other bytes makes it allocate what they announce.  Then, while the scheduler has
  no worker, a progress line and at most ``wait`` s more.

Errors are :class:`ClusterError` with one line, naming what to check.
"""

from __future__ import annotations

import asyncio
import ipaddress
import re
import socket
import time
from collections.abc import Callable
from typing import Any

#: Default of ``--cluster-timeout`` [s]: the TCP connection, Dask's handshake and each
#: answer of the scheduler must come within it.
CONNECT_TIMEOUT_S = 10.0
#: Default of ``--cluster-wait`` [s]: how long a scheduler without workers is waited for.
WORKER_WAIT_S = 60.0
#: How often the scheduler is asked for its workers while it has none [s].
POLL_S = 0.5

_HOST_LABEL = re.compile(r'(?!-)[A-Za-z0-9-]{1,63}(?<!-)')


class ClusterError(Exception):
    """The cluster cannot be used: one line (the address is said by the caller)."""


def check_address(text: str) -> tuple[str, int]:
    """(host, port) of a scheduler address ``tcp://HOST:PORT``; ValueError with the reason
    (one line, starting with what is wrong)."""
    usage = f'must be a Dask scheduler address tcp://HOST:PORT, got {text!r}'
    m = re.fullmatch(r'([A-Za-z][A-Za-z0-9+.-]*)://(.*)', text)
    if m is None:
        raise ValueError(usage)
    scheme, rest = m.group(1).lower(), m.group(2)
    if scheme == 'tls':
        raise ValueError(
            f'{text}: tls:// needs TLS certificates on both sides, which the study does not '
            'take; use tcp:// (on a trusted network, or through an SSH tunnel: ssh -L)'
        )
    if scheme != 'tcp':
        raise ValueError(f'{text}: scheme {scheme}:// not supported; {usage}')
    if rest.startswith('['):  # [IPv6]:PORT
        m6 = re.fullmatch(r'\[([^\]]*)\]:([^:]*)', rest)
        if m6 is None:
            raise ValueError(usage)
        host, port_text = m6.groups()
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f'{text}: {host!r} is not an IPv6 address') from None
    else:
        host, sep, port_text = rest.rpartition(':')
        if not sep or not host:
            raise ValueError(usage)
        if not _valid_host(host):
            raise ValueError(f'{text}: {host!r} is not a host name or an IP address')
    if not re.fullmatch(r'[0-9]{1,5}', port_text) or not 1 <= int(port_text) <= 65535:
        raise ValueError(f'{text}: the port must be 1..65535, got {port_text!r}')
    return host, int(port_text)


def _valid_host(host: str) -> bool:
    """A DNS host name (RFC 1123 labels) or an IPv4 address (an IPv6 one needs brackets)."""
    if re.fullmatch(r'[0-9.]+', host):
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            return False
        return True
    name = host[:-1] if host.endswith('.') else host
    return 0 < len(name) <= 253 and all(_HOST_LABEL.fullmatch(x) for x in name.split('.'))


def wait_for_scheduler(
    address: str,
    timeout: float = CONNECT_TIMEOUT_S,
    wait: float = WORKER_WAIT_S,
    say: Callable[[str], None] | None = None,
) -> int:
    """Check that a Dask scheduler answers at ``address`` and has a worker; return its
    worker count.  ``timeout`` [s] bounds the connection and each answer, ``wait`` [s] the
    wait for a first worker (``say`` gets a line when the wait starts and whenever the
    count changes).  :class:`ClusterError` otherwise, within ``timeout + wait`` s plus a
    few answers."""
    host, port = check_address(address)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except ConnectionRefusedError:
        raise ClusterError(
            f'nothing listens there (connection refused): is the scheduler running '
            f'(dask scheduler --port {port})?'
        ) from None
    except TimeoutError:
        raise ClusterError(
            f'no connection within {timeout:g} s: check the host, the port and any firewall'
        ) from None
    except socket.gaierror as exc:
        raise ClusterError(f'cannot resolve host {host!r} ({exc.strerror})') from None
    except OSError as exc:
        raise ClusterError(f'cannot connect ({exc.strerror or exc})') from None
    return asyncio.run(_ask(address, timeout, wait, say or (lambda _text: None)))


async def _ask(address: str, timeout: float, wait: float, say: Callable[[str], None]) -> int:
    from distributed.comm import connect

    not_dask = (
        f'no Dask scheduler answered within {timeout:g} s (something listens there, but '
        "it does not speak Dask's protocol, or is stuck): check the address "
        '(--cluster-timeout to wait longer)'
    )
    try:
        comm = await asyncio.wait_for(connect(address, timeout=timeout), timeout)
    except TimeoutError:
        raise ClusterError(not_dask) from None
    except Exception as exc:  # any answer that is not Dask's handshake
        raise ClusterError(
            f'not a Dask scheduler (its answer to the handshake: {type(exc).__name__})'
        ) from None
    try:
        deadline = time.monotonic() + wait
        said = -1
        while True:
            n = _workers(await _identity(comm, timeout, not_dask))
            if n > 0:
                if said >= 0:
                    say(f'study: {n} worker(s) connected to {address}')
                return n
            if said != n:
                say(
                    f'study: waiting for workers on {address}: {n} connected '
                    f'(at most {wait:g} s, --cluster-wait)'
                )
                said = n
            if time.monotonic() >= deadline:
                raise ClusterError(
                    f'no worker joined the scheduler within {wait:g} s: start workers '
                    f'(dask worker {address} --nthreads 1), or wait longer (--cluster-wait)'
                )
            await asyncio.sleep(min(POLL_S, max(0.0, deadline - time.monotonic())))
    finally:
        comm.abort()  # (close() would wait for the peer)


async def _identity(comm: Any, timeout: float, not_dask: str) -> dict[str, Any]:
    """The peer's answer to Dask's ``identity`` call: must be a scheduler's."""
    try:
        await asyncio.wait_for(comm.write({'op': 'identity', 'n_workers': 0}), timeout)
        reply = await asyncio.wait_for(comm.read(), timeout)
    except TimeoutError:
        raise ClusterError(not_dask) from None
    except Exception as exc:  # a closed or garbled link
        text = f'the scheduler did not answer (identity: {type(exc).__name__}: {exc})'
        raise ClusterError(text.splitlines()[0]) from None
    kind = reply.get('type') if isinstance(reply, dict) else None
    if kind != 'Scheduler':
        raise ClusterError(
            f'not a Dask scheduler (it says it is {kind or "something else"!s}): point '
            "--cluster at the scheduler's address"
        )
    return reply


def _workers(identity: dict[str, Any]) -> int:
    n = identity.get('n_workers')
    return int(n) if isinstance(n, int) else len(identity.get('workers') or {})
