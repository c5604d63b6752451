"""City model files as they are downloaded: gzip-compressed files (`*.gml.gz`, `*.city.json.gz`,
`*.jsonl.gz`) and ZIP archives of tiles.

A gzip file is read as a stream wherever a model file is read (`open_model`, `read_model_text`):
it is never unpacked to disk, and the tile index keeps its entry by the compressed file's size
and time. A ZIP archive is unpacked once per process into a temporary directory that lives until
the process ends (`expand_archive`): every reader, the tile index, the terrain reader and the
write-back of a corrected model then see ordinary files (or gzip members, read as streams). A
damaged archive raises InputError naming it.
"""

from __future__ import annotations

import gzip
import io
import logging
import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO

from ..errors import InputError

logger = logging.getLogger(__name__)

GZIP_SUFFIX = ".gz"
ZIP_SUFFIX = ".zip"
#: The two bytes every gzip stream starts with (RFC 1952).
GZIP_MAGIC = b"\x1f\x8b"
#: Largest share of an archive's unpacked size to its packed size that is still taken for a
#: tile archive (CityGML deflates about 10-20 times); beyond it the archive is refused as a
#: likely zip bomb.
MAX_ZIP_RATIO = 200.0

CITYGML_SUFFIXES = (".gml", ".xml")
CITYJSON_SUFFIXES = (".json", ".jsonl")

_UNPACKED: dict[tuple, tuple[tempfile.TemporaryDirectory, list[Path]]] = {}


def is_gzip(path: Path) -> bool:
    """Whether `path` names a gzip-compressed file (by its suffix)."""
    return Path(path).suffix.lower() == GZIP_SUFFIX


def is_zip(path: Path) -> bool:
    return Path(path).suffix.lower() == ZIP_SUFFIX


def is_model_file(path: Path) -> bool:
    """Whether the name is that of a CityGML or CityJSON file, plain or gzip-compressed."""
    return model_suffix(path) in CITYGML_SUFFIXES + CITYJSON_SUFFIXES


def inner_name(path: Path) -> str:
    """The file name without a gzip suffix: "3920_5820.gml.gz" -> "3920_5820.gml"."""
    name = Path(path).name
    return name[: -len(GZIP_SUFFIX)] if is_gzip(Path(name)) else name


def model_suffix(path: Path) -> str:
    """The lower-case suffix of the model format, under a gzip suffix: ".gml", ".json"."""
    return Path(inner_name(path)).suffix.lower()


class _GzipReader(io.RawIOBase):
    """A gzip stream whose damage (a cut or corrupted file) raises InputError naming it."""

    def __init__(self, path: Path):
        self.path = path
        self._stream = gzip.open(path, "rb")

    def readable(self) -> bool:
        return True

    def read(self, size: int = -1) -> bytes:
        try:
            return self._stream.read(size)
        except (EOFError, zlib.error, gzip.BadGzipFile) as error:
            raise InputError(f"damaged gzip file: {error}", self.path) from None

    def readinto(self, buffer) -> int:
        data = self.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)

    def close(self) -> None:
        self._stream.close()
        super().close()


def open_model(path: str | Path) -> BinaryIO:
    """A binary stream of a model file (to close, or use in `with`), decompressed when it is
    gzip-compressed. OSError for a file that cannot be opened; InputError for a damaged gzip
    stream (while reading)."""
    path = Path(path)
    return _GzipReader(path) if is_gzip(path) else open(path, "rb")


def read_model_head(path: str | Path, size: int) -> bytes:
    """The first `size` bytes of a model file's (decompressed) content."""
    with open_model(path) as stream:
        return stream.read(size)


def read_model_text(path: str | Path) -> str:
    """A model file's whole (decompressed) content as UTF-8 text (UnicodeDecodeError as
    Python raises it)."""
    with open_model(path) as stream:
        return stream.read().decode("utf-8")


def expand_archive(path: str | Path) -> list[Path]:
    """The city model files (CityGML, CityJSON, plain or gzip) inside the ZIP archive at `path`,
    unpacked once per process into a temporary directory, in the archive's order of names.
    InputError for a damaged archive or one without model files."""
    path = Path(path)
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key in _UNPACKED:
        return list(_UNPACKED[key][1])
    try:
        with zipfile.ZipFile(path) as archive:
            members = sorted((m for m in archive.infolist()
                              if not m.is_dir() and is_model_file(Path(m.filename))
                              and not Path(m.filename).name.startswith(".")),
                             key=lambda m: m.filename)
            if not members:
                raise InputError("ZIP archive holds no CityGML (*.gml, *.xml) or CityJSON "
                                 "(*.json, *.jsonl) files", path)
            unpacked = sum(m.file_size for m in members)
            if unpacked > MAX_ZIP_RATIO * max(stat.st_size, 1):
                raise InputError(f"ZIP archive would unpack to {unpacked / 1e6:.0f} MB from "
                                 f"{stat.st_size / 1e6:.1f} MB: refused as damaged", path)
            scratch = tempfile.TemporaryDirectory(prefix="colmap_citymodel_zip_")
            files = [_unpack(archive, member, Path(scratch.name), k)
                     for k, member in enumerate(members)]
    except zipfile.BadZipFile as error:
        raise InputError(f"damaged ZIP archive: {error}", path) from None
    except (zlib.error, EOFError, OSError) as error:
        raise InputError(f"damaged ZIP archive: {error}", path) from None
    _UNPACKED[key] = (scratch, files)
    logger.info("unpacked %d city model file(s) (%.1f MB) of %s", len(files), unpacked / 1e6,
                path)
    return list(files)


def _unpack(archive: zipfile.ZipFile, member: zipfile.ZipInfo, directory: Path,
            number: int) -> Path:
    """One member into `directory` under its own file name (a number first when two members
    of different folders share a name); its CRC is checked while it is copied."""
    name = Path(member.filename).name
    target = directory / name
    if target.exists():
        target = directory / f"{number:04d}_{name}"
    try:
        with archive.open(member) as source, open(target, "wb") as out:
            shutil.copyfileobj(source, out)
    except zipfile.BadZipFile as error:  # a member's CRC or header is wrong
        raise InputError(f"damaged ZIP archive: {member.filename}: {error}",
                         archive.filename) from None
    return target
