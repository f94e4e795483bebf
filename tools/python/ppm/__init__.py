"""A groundstation's client for ppm's udp-ingress: channel commands over UDP.

One :class:`Sender` talks to one udp-ingress (``"host:port"``, or
``"[::1]:5005"`` for IPv6). It builds the JSON of each command form, numbers
it with ``seq`` (microseconds since the epoch, so a restarted groundstation
is never taken for a replay), names the output it is for (``name``, the
output's name in the ingress's configuration; sent as ``to``), signs it when
given the ingress's key file, and checks every value before anything is
sent. Several vehicles: one sender each. Pure standard library, Python 3.9
or newer.

Example::

    import time
    import ppm

    s = ppm.Sender("127.0.0.1:5005")            # key_file=..., name="rover" to sign
    for i in range(250):                        # 5 s at 50 Hz
        s.send([1500, 1500, 1000 + 2 * i, 1500])  # us, in the transmitter's order
        time.sleep(0.02)
    s.send(ail=1600, thr=1100)                  # named channels, us
    s.send_norm(ail=0.2, thr=-1)                # -1..1 on every channel
    s.send_units(ail=3.0)                       # a channel's unit range (ppm.channel.ail)
    print(s.status()["datagrams"]["applied"])

The wire protocol, the signature and the status reply are described in the
project's docs/protocol.md, docs/security.md ("Authenticated commands") and
docs/status.md ("Status queries").
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import numbers
import os
import re
import socket
import stat
import time
from collections.abc import Iterable, Mapping
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

__all__ = [
    "Sender",
    "PpmError",
    "StatusTimeout",
    "KeyFileError",
    "load_key",
    "sign",
    "envelope",
    "status_query",
    "read_log",
    "joined",
    "VALUE_MIN_US",
    "VALUE_MAX_US",
]

__version__ = "0.1.0"

#: Lowest microsecond value a command may carry (udp-ingress rejects lower as out_of_range).
VALUE_MIN_US = 500.0
#: Highest microsecond value a command may carry.
VALUE_MAX_US = 2500.0
#: Most channels a frame has.
MAX_CHANNELS = 16
#: The status query as udp-ingress recognises it.
STATUS_QUERY = b'{"get":"status"}'
#: The telemetry query: the status reply's ``telemetry`` member alone.
TELEMETRY_QUERY = b'{"get":"telemetry"}'
#: The size status queries are padded to, as ppm's other tools pad theirs: a
#: third of the largest reply (4200 bytes), which is never more than 3 times
#: the query, so any source gets it.
STATUS_QUERY_PADDED_LEN = 1400
#: The largest key file read, like udp-ingress (64 hex characters and whitespace).
KEY_MAX_BYTES = 4096

_NAME = re.compile(r"(ail|ele|thr|rud|aux([1-9]|1[0-2]))\Z")
_OUTPUT = re.compile(r"[A-Za-z0-9_-]{1,64}\Z")
_HEX = frozenset("0123456789abcdefABCDEF")

Number = Union[int, float]


class PpmError(Exception):
    """An error of this package (besides :class:`ValueError` for bad input)."""


class StatusTimeout(PpmError, TimeoutError):
    """No status reply came in time."""


class KeyFileError(PpmError, ValueError):
    """The key file is refused, for the same reasons udp-ingress refuses it."""


def load_key(path: Union[str, "os.PathLike[str]"]) -> bytes:
    """Reads a key file: 32 bytes as 64 hex characters, whitespace around them.

    Refused, as udp-ingress refuses it, when it is not a regular file of at
    most 4096 bytes, when group or others may read or write it (POSIX), when
    it cannot be read, or when it is not 64 hex characters.
    """
    shown = os.fspath(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(shown, flags)  # not blocking: a FIFO is refused, not waited on
    except OSError as e:
        raise KeyFileError(f"cannot read auth key file {shown}: {e.strerror}") from e
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise KeyFileError(
                f"cannot read auth key file {shown}: it is {_kind(st.st_mode)}, not a regular file"
            )
        if st.st_size > KEY_MAX_BYTES:
            raise KeyFileError(
                f"cannot read auth key file {shown}: it holds {st.st_size} bytes or more, "
                f"and this file is never larger than {KEY_MAX_BYTES}"
            )
        mode = stat.S_IMODE(st.st_mode)
        if os.name == "posix" and mode & 0o077:
            raise KeyFileError(
                f"auth key file {shown} is accessible by group or others (mode {mode:04o}): "
                f"run `chmod 600 {shown}`"
            )
        data = os.read(fd, KEY_MAX_BYTES + 1)
    finally:
        os.close(fd)
    if len(data) > KEY_MAX_BYTES:
        raise KeyFileError(
            f"cannot read auth key file {shown}: it holds {len(data)} bytes or more, "
            f"and this file is never larger than {KEY_MAX_BYTES}"
        )
    text = data.decode("utf-8", errors="replace").strip()
    hint = (
        f"auth key file {shown} must hold the key as 64 hex characters "
        "(32 bytes, e.g. from `openssl rand -hex 32`)"
    )
    if len(text) != 64:
        raise KeyFileError(f"{hint}: found {len(text)} characters (whitespace around them aside)")
    if not set(text) <= _HEX:
        raise KeyFileError(f"{hint}: not hex")
    return bytes.fromhex(text)


def _kind(mode: int) -> str:
    for test, what in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return what
    return "not a regular file"


def sign(key: bytes, msg: str) -> str:
    """HMAC-SHA256 of the UTF-8 bytes of ``msg`` under ``key``, lowercase hex.

    >>> sign(bytes(range(32)), '{"ch":[1500,1500,1000,1500],"seq":1,"to":"rover"}')
    '19eef9dbcc55a46bd2faaba57d00dc42b04194b7b57493491f68d3032314e1fc'
    """
    return hmac.new(key, msg.encode("utf-8"), hashlib.sha256).hexdigest()


def envelope(key: bytes, msg: str) -> str:
    """The signed datagram carrying the command text ``msg`` (which names
    its output in ``to``: udp-ingress refuses a signed command without it).

    >>> print(envelope(bytes(range(32)), '{"ch":[1500,1500,1000,1500],"seq":1,"to":"rover"}'))
    {"msg":"{\\"ch\\":[1500,1500,1000,1500],\\"seq\\":1,\\"to\\":\\"rover\\"}","mac":"19eef9dbcc55a46bd2faaba57d00dc42b04194b7b57493491f68d3032314e1fc"}
    """
    return _dumps({"msg": msg, "mac": sign(key, msg)})


def status_query(size: int = STATUS_QUERY_PADDED_LEN) -> bytes:
    """``{"get":"status"}`` padded with trailing spaces to ``size`` bytes.

    >>> len(status_query()), status_query().rstrip()
    (1400, b'{"get":"status"}')
    """
    return STATUS_QUERY.ljust(size, b" ")


def parse_target(target: str) -> Tuple[str, int]:
    """Splits ``"host:port"`` or ``"[v6 address]:port"`` into host and port.

    >>> parse_target("[::1]:5005")
    ('::1', 5005)
    >>> parse_target("rover.local:5006")
    ('rover.local', 5006)
    """
    if not isinstance(target, str):
        raise ValueError(f"target must be a string \"host:port\", got {target!r}")
    host, sep, port = target.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise ValueError(
            f"target {target!r}: write an IPv6 address in brackets, e.g. \"[::1]:5005\""
        )
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(
            f"target {target!r} is not \"host:port\" (e.g. \"127.0.0.1:5005\", \"[::1]:5005\")"
        )
    return host, int(port)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def _number(what: str, v: Any) -> Number:
    """``v`` as a finite JSON number, or a ValueError naming ``what``."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise ValueError(f"{what} is {v!r}, not a number")
    x: Number = int(v) if isinstance(v, numbers.Integral) else float(v)
    if not math.isfinite(x):
        raise ValueError(f"{what} is {x}, not a finite number")
    return x


def _us(what: str, v: Any) -> Number:
    x = _number(what, v)
    if not VALUE_MIN_US <= x <= VALUE_MAX_US:
        raise ValueError(f"{what} = {x} us is outside {VALUE_MIN_US:g}..{VALUE_MAX_US:g}")
    return x


def _named(channels: Dict[str, Any], check: Callable[[str, Any], Number]) -> Dict[str, Number]:
    if not channels:
        raise ValueError("no channel given")
    out = {}
    for name, v in channels.items():
        if name == "seq":
            raise ValueError("`seq` is not a channel: the Sender numbers commands itself (seq=True)")
        if name == "to":
            raise ValueError("`to` is not a channel: the Sender names the output itself (name=...)")
        if not _NAME.match(name):
            raise ValueError(f"no channel `{name}`: channels are ail, ele, thr, rud, aux1 .. aux12")
        out[name] = check(name, v)
    return out


class Sender:
    """Sends channel commands to one udp-ingress, and asks it for its status.

    ``target`` is ``"host:port"`` (``"[::1]:5005"`` for IPv6). ``name`` is
    the name of the output the commands are for (its ``name`` in the
    ingress's configuration): every command carries it as ``to``, and
    udp-ingress refuses a command for another output. With ``key_file``
    (the ingress's ``ingress.auth_key``: 64 hex characters, mode 600) every
    command is signed, name included, so a copy sent to another vehicle
    with the same key is refused; a key needs ``name``. With ``seq`` (the default; a key
    needs it) every command carries a ``seq``: the time in microseconds, or
    one more than the last, whichever is greater, so it keeps growing across
    restarts. One sender per target; each numbers its own commands.

    Each ``send*`` method checks its values first (:class:`ValueError` naming
    the problem, and nothing is sent), then sends one datagram and returns
    it. udp-ingress does not answer commands: ask :meth:`status` for its
    counters.
    """

    def __init__(
        self,
        target: str,
        key_file: Optional[Union[str, "os.PathLike[str]"]] = None,
        seq: bool = True,
        name: Optional[str] = None,
    ) -> None:
        host, port = parse_target(target)
        if key_file is not None and not seq:
            raise ValueError(
                "a key needs seq=True: udp-ingress refuses signed commands without a seq (no_seq)"
            )
        if name is not None and not (isinstance(name, str) and _OUTPUT.match(name)):
            raise ValueError(
                f"name {name!r} is no output name: 1 to 64 letters, digits, `-` or `_`"
            )
        if key_file is not None and name is None:
            raise ValueError(
                "a key needs name=, the name of the output the commands are for (its `name` in "
                "the ingress's configuration): it is signed with each command, and udp-ingress "
                "refuses signed commands without it (no_to) or for another output (wrong_output)"
            )
        self.target = target
        self.name = name
        self._key = load_key(key_file) if key_file is not None else None
        self._numbered = seq
        self._seq = 0
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        if not infos:
            raise PpmError(f"{target} resolves to no address")
        self._family, _, _, _, self.address = infos[0]
        self._socket = socket.socket(self._family, socket.SOCK_DGRAM)

    @property
    def last_seq(self) -> Optional[int]:
        """The ``seq`` of the last command sent, ``None`` before the first (or without seq)."""
        return self._seq or None

    def send(self, values: Optional[Iterable[Number]] = None, **channels: Number) -> bytes:
        """Sends microsecond values: a list in the transmitter's channel order,
        or named channels (``ail=1500, thr=1000, aux1=1800``).

        Values may be fractional; each must lie in 500..2500 us (udp-ingress
        clamps it to its channel's ``min_us..max_us``). Channels left out
        take their configured default.
        """
        if values is not None and channels:
            raise ValueError("give either a list of values or named channels, not both")
        if values is None:
            return self._send(_named(channels, lambda k, v: _us(f"channel `{k}`", v)))
        if isinstance(values, (str, bytes, Mapping)) or not isinstance(values, Iterable):
            raise ValueError(f"values must be a list of microseconds, got {type(values).__name__}")
        values = list(values)  # a tuple, a numpy array, ...
        if not 1 <= len(values) <= MAX_CHANNELS:
            raise ValueError(f"{len(values)} values: a command gives 1 to {MAX_CHANNELS} channels")
        us: List[Number] = [_us(f"channel {i + 1}", v) for i, v in enumerate(values)]
        return self._send(us)

    def send_norm(self, **channels: Number) -> bytes:
        """Sends named channels normalised to -1..1 (-1 is the channel's
        minimum, 1 its maximum; values beyond are clamped by udp-ingress)."""
        return self._send({"norm": _named(channels, lambda k, v: _number(f"norm `{k}`", v))})

    def send_units(self, **channels: Number) -> bytes:
        """Sends named channels in the engineering units of their unit range
        (``ppm.channel.NAME.unit_min``/``unit_max``; udp-ingress rejects a
        channel without one as unknown_channel)."""
        return self._send({"units": _named(channels, lambda k, v: _number(f"units `{k}`", v))})

    def _send(self, command: Union[List[Number], Dict[str, Any]]) -> bytes:
        extra: Dict[str, Any] = {}
        if self._numbered:
            self._seq = max(self._seq + 1, time.time_ns() // 1000)
            extra["seq"] = self._seq
        if self.name is not None:
            extra["to"] = self.name
        if extra:
            command = {"ch": command, **extra} if isinstance(command, list) else {**command, **extra}
        text = _dumps(command)
        datagram = (envelope(self._key, text) if self._key is not None else text).encode("utf-8")
        self._socket.sendto(datagram, self.address)
        return datagram

    def status(self, timeout: float = 1.0) -> Dict[str, Any]:
        """Asks udp-ingress for its status and returns the reply (a dict with
        ``datagrams``, ``ppmd``, ...: see docs/status.md, "Status queries").

        The query is padded to 1400 bytes, so any source gets the reply (no
        reply is more than 3 times its query, unless the source is in
        ``ingress.status_allow``); when the answer is ``{"pad_to": N}`` the
        query is sent once more, padded to N. Raises :class:`StatusTimeout`
        when no reply comes within ``timeout`` seconds, and at once when the
        target refuses the query (nothing listens there).
        """
        return self._query(STATUS_QUERY, timeout)

    def telemetry(self, timeout: float = 1.0) -> Optional[Dict[str, Any]]:
        """Asks udp-ingress for the flight controller's telemetry (a CRSF
        output on a serial port) and returns the status reply's
        ``telemetry`` member (``battery``, ``attitude``, ``gps``,
        ``flight_mode``, ...: see docs/status.md), or None for an output
        without telemetry. Padded, retried and raising as :meth:`status`.
        """
        return self._query(TELEMETRY_QUERY, timeout).get("telemetry")

    def _query(self, query: bytes, timeout: float) -> Dict[str, Any]:
        if not timeout > 0:
            raise ValueError(f"timeout must be more than 0 s, got {timeout!r}")
        with socket.socket(self._family, socket.SOCK_DGRAM) as s:
            s.settimeout(timeout)
            s.connect(self.address)  # only the target's reply; "nothing listens" is reported
            reply = self._ask(s, query, STATUS_QUERY_PADDED_LEN, timeout)
            if set(reply) == {"pad_to"}:
                n = reply["pad_to"]
                if isinstance(n, bool) or not isinstance(n, int) or not len(query) <= n <= 65_000:
                    raise PpmError(f"{self.target} asked for a status query of {n!r} bytes")
                reply = self._ask(s, query, max(n, STATUS_QUERY_PADDED_LEN), timeout)
                if set(reply) == {"pad_to"}:
                    raise PpmError(f"{self.target} still answers {reply} to a query of {n} bytes")
            return reply

    def _ask(self, s: socket.socket, query: bytes, size: int, timeout: float) -> Dict[str, Any]:
        try:
            s.send(query.ljust(size, b" "))
            data = s.recv(65_536)
        except socket.timeout:
            raise StatusTimeout(
                f"no status reply from {self.target} within {timeout:g} s: is udp-ingress running and "
                "listening there (ingress.listen)? A firewall, or an ingress.allow without this "
                "machine, may also drop the datagrams"
            ) from None
        except ConnectionRefusedError:
            # No reply will come: the same StatusTimeout as for silence, at once.
            raise StatusTimeout(
                f"no status reply from {self.target}: it refused the query (port unreachable), "
                "nothing listens there; is udp-ingress running, with this ingress.listen?"
            ) from None
        try:
            reply = json.loads(data)
        except ValueError:
            reply = None
        if not isinstance(reply, dict):
            raise PpmError(f"the status reply from {self.target} is not a JSON object: {data[:200]!r}")
        return reply

    def close(self) -> None:
        """Closes the socket."""
        self._socket.close()

    def __enter__(self) -> "Sender":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        signed = ", signed" if self._key is not None else ""
        name = f", name={self.name!r}" if self.name is not None else ""
        return f"Sender({self.target!r}{name}{signed}, seq={self._numbered})"


def read_log(path: Union[str, "os.PathLike[str]"]) -> List[Dict[str, Any]]:
    """The rows of a JSON-lines log of ppmd (its frame log, ``ppmd.frame_log``,
    or its read-back log, ``ppmd.readback_log``), in file order. A last line
    cut short by a writer still running is left out; any other line that is
    not JSON raises :class:`PpmError` naming the file and the line."""
    rows: List[Dict[str, Any]] = []
    with open(path, encoding="utf-8") as f:
        lines = f.read().split("\n")
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except ValueError as e:
            if i == len(lines) - 1:
                break
            raise PpmError(f"{os.fspath(path)} line {i + 1}: not a JSON row ({e})") from None
    return rows


def joined(
    frame_log: Union[str, "os.PathLike[str]", None],
    readback_log: Union[str, "os.PathLike[str]"],
) -> Iterable[Dict[str, Any]]:
    """Joins the three streams, one row per frame read back from the radio:
    ``read`` (the read-back log's row: what the radio transmitted, ``ch_us``,
    its ``match`` and ``state``), ``line`` (the frame log's newest row of a
    frame the line carried that began before the read frame did: what ppm
    sent) and ``command`` (that frame's command: ``seq``, ``ingress_seq``,
    ``recv_mono_ns``, ``recv_real_ns``; ``None`` for a failsafe frame), and
    ``lag_ms``, the read frame's start after the line frame's. All times are
    CLOCK_MONOTONIC ns (``mono_ns``) with the wall time beside them
    (``real_ns``), as both logs write them. Without a frame log (``None``: a
    pilot's radio recorded with ``ppm-capture``) ``line`` and ``command`` are
    ``None``.

    >>> import tempfile, os.path
    >>> d = tempfile.mkdtemp()
    >>> f, r = os.path.join(d, "f.jsonl"), os.path.join(d, "r.jsonl")
    >>> _ = open(f, "w").write('{"type":"frame","mono_ns":100,"seq":7,"ingress_seq":1,'
    ...     '"recv_mono_ns":90,"recv_real_ns":5,"ch_us":[1300.0]}\\n')
    >>> _ = open(r, "w").write('{"type":"read","mono_ns":50,"ch_us":[1500.0]}\\n'
    ...     '{"type":"readback","mono_ns":60,"from":"no_input","to":"following"}\\n'
    ...     '{"type":"read","mono_ns":2000100,"ch_us":[1300.0],"match":true}\\n')
    >>> [(j["read"]["ch_us"], j["line"] and j["line"]["ch_us"], j["command"] and j["command"]["seq"], j["lag_ms"])
    ...  for j in joined(f, r)]
    [([1500.0], None, None, None), ([1300.0], [1300.0], 7, 2.0)]
    """
    frames = [] if frame_log is None else [r for r in read_log(frame_log) if r.get("type") == "frame"]
    frames.sort(key=lambda r: r["mono_ns"])
    i = -1
    for row in read_log(readback_log):
        if row.get("type") != "read":
            continue
        while i + 1 < len(frames) and frames[i + 1]["mono_ns"] <= row["mono_ns"]:
            i += 1
        line = frames[i] if i >= 0 else None
        command = None
        if line is not None and line.get("ingress_seq") is not None:
            command = {k: line.get(k) for k in ("seq", "ingress_seq", "recv_mono_ns", "recv_real_ns")}
        yield {
            "read": row,
            "line": line,
            "command": command,
            "lag_ms": None if line is None else (row["mono_ns"] - line["mono_ns"]) / 1e6,
        }
