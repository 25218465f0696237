"""The shared types of the scan sources: a source's name (`SourceName`, `parse_source`), its
errors, and `ScanSource`, the scans of one source and its summary.

`twin.lidar.sources` opens any name as a `ScanSource`; the readers of one kind of source (an
Ouster's organised cloud, nebula's Hesai cloud) depend on these types only, not on the module
that dispatches to them, as ouster-sdk's and velodyne_decoder's readers depend on their shared
types.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

from twin.core import vlp16
from twin.core.errors import AimbenchError
from twin.core.scan import Scan

#: What every error about a source name says can be given.
KINDS_HELP = ("a .pcap/.pcapng capture, udp://HOST:PORT, a ROS 1 .bag, a ROS 2 bag (folder, "
              ".db3 or .mcap), a .pcd file or an Ouster .osf file")
DEFAULT_UDP = f"udp://0.0.0.0:{vlp16.DATA_PORT}"

_MAGIC = (
    (b"\xd4\xc3\xb2\xa1", "pcap"), (b"\xa1\xb2\xc3\xd4", "pcap"),
    (b"\x4d\x3c\xb2\xa1", "pcap"), (b"\xa1\xb2\x3c\x4d", "pcap"),
    (b"\x0a\x0d\x0d\x0a", "pcap"),  # pcapng section header
    (b"#ROSBAG", "bag"), (b"SQLite format 3\x00", "bag"), (b"\x89MCAP", "bag"),
    (b"# .PCD", "pcd"), (b"VERSION", "pcd"), (b"FIELDS", "pcd"),
)
_SUFFIXES = {".pcap": "pcap", ".pcapng": "pcap", ".bag": "bag", ".db3": "bag", ".mcap": "bag",
             ".pcd": "pcd", ".osf": "osf"}
#: An OSF file (Ouster's format, ouster-sdk) is a size-prefixed flatbuffer: its identifier
#: follows the size and the root offset.
_OSF_ID = (8, b"OSF$")


class SourceError(AimbenchError):
    """A source name that names nothing readable (bad URL, no such file, unknown format)."""


class SourceExhaustedError(SourceError):
    """A recorded source has no more whole scans."""


@dataclass(frozen=True)
class SourceName:
    """A parsed source name: its ``kind`` (pcap, udp, bag, pcd, osf) and where it is."""

    text: str
    kind: str
    path: Path | None = None
    host: str = ""
    port: int = 0
    topic: str | None = None

    @property
    def live(self) -> bool:
        return self.kind == "udp"

    def __str__(self) -> str:
        return self.text


def parse_source(text: str | Path) -> SourceName:
    """The `SourceName` of a name (module docstring); `SourceError` if it names nothing."""
    text = str(text)
    if "://" in text:
        scheme, _, rest = text.partition("://")
        if scheme.lower() != "udp":
            raise SourceError(f"{text}: unknown source scheme {scheme}://; give {KINDS_HELP}")
        host, sep, port = rest.rpartition(":")
        try:
            number = int(port)
            if not sep or not 0 < number < 65536:
                raise ValueError
        except ValueError:
            raise SourceError(f"{text}: give the live sensor as udp://HOST:PORT, e.g. "
                              f"{DEFAULT_UDP} (every interface, the VLP-16's data port)") from None
        return SourceName(text, "udp", host=host.strip("[]") or "0.0.0.0", port=number)
    path, topic = Path(text), None
    if not path.exists() and "#" in text:
        head, _, topic = text.rpartition("#")
        path = Path(head)
    if not path.exists():
        raise SourceError(f"{path}: no such file or folder; give {KINDS_HELP}")
    return SourceName(text, _kind_of(path), path=path, topic=topic or None)


def _kind_of(path: Path) -> str:
    if path.is_dir():
        if (path / "metadata.yaml").is_file() or any(path.glob("*.db3")) or any(
                path.glob("*.mcap")):
            return "bag"
        raise SourceError(f"{path}: a folder, but not a ROS 2 bag (no metadata.yaml, .db3 or "
                          f".mcap in it); give {KINDS_HELP}")
    try:
        with path.open("rb") as f:
            head = f.read(16)
    except OSError as exc:
        raise SourceError(f"{path}: cannot read it ({exc.strerror})") from None
    for magic, kind in _MAGIC:
        if head.startswith(magic):
            return kind
    at, osf_id = _OSF_ID
    if head[at:at + len(osf_id)] == osf_id:
        return "osf"
    kind = _SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise SourceError(f"{path}: not a format aimbench reads (starts with "
                          f"{head[:8].hex() or 'nothing'}); give {KINDS_HELP}")
    return kind  # its own reader says what is wrong with it (empty, cut off, damaged)


class ScanSource(abc.ABC):
    """The scans of one named source, in order (iterate once), and a summary of the source.

    ``max_scans``: stop after this many whole scans (partial ones, at a stream's ends, are
    yielded and flagged but not counted). ``extra``: more summary entries, values or functions
    called when the summary is made (a socket's or a bag's counts). ``closer``: releases the
    file, socket or bag. Use as a context manager, or call `close`.
    """

    def __init__(self, name: SourceName, max_scans: int | None = None,
                 extra: dict | None = None, closer: Callable[[], None] | None = None) -> None:
        if max_scans is not None and max_scans < 1:
            raise SourceError(f"--scans {max_scans}: give at least 1 scan")
        self.name = name
        self.max_scans = max_scans
        self.whole = 0
        self._extra = extra or {}
        self._closer = closer

    @abc.abstractmethod
    def _scans(self) -> Iterator[Scan]:
        """Every scan of the source."""

    def __iter__(self) -> Iterator[Scan]:
        try:
            for scan in self._scans():
                yield scan
                if not scan.meta.get("partial"):
                    self.whole += 1
                    if self.max_scans is not None and self.whole >= self.max_scans:
                        return
        finally:
            self.close()

    @abc.abstractmethod
    def _summary(self) -> dict:
        """The figures of this kind of source."""

    def summary(self) -> dict:
        """What the source held (valid once iteration ended): the `aimbench info` object."""
        out = {"source": self.name.text, "kind": self.name.kind, **self._summary()}
        for key, value in self._extra.items():
            out[key] = value() if callable(value) else value
        return out

    def close(self) -> None:
        """Release the file, socket or bag (once)."""
        if self._closer is not None:
            closer, self._closer = self._closer, None
            closer()

    def __enter__(self) -> ScanSource:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
