"""What the tools may write, checked before any work: never into one of their inputs, never over a file that
nmnet did not write; and results written whole or not at all.

Every file the tools write carries a mark that tells it apart from a user's: an .mcap's header names this
library, a JSON object has ``written_by``, a PNG a ``Software`` text chunk, a checkpoint ``written_by`` in its
pickle. An existing file without the mark (a recording, its ``metadata.yaml``, a user's notes) is refused with
the reason, as ``ros2 bag record`` and rosbags' converters refuse an existing output.
"""

from __future__ import annotations

import json
import math
import os
import uuid
import zipfile
from collections.abc import Callable, Iterable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    from matplotlib.figure import Figure

LIBRARY = "nmnet_ros"  # the mark: an .mcap header's library, a JSON's or checkpoint's written_by, a PNG's Software


def written_by() -> str:
    """The mark's value: ``nmnet_ros X.Y.Z`` (the installed version, where there is one)."""
    try:
        return f"{LIBRARY} {version(LIBRARY)}"
    except PackageNotFoundError:
        return LIBRARY


def _png_software(path: Path) -> str | None:
    """A PNG's ``Software`` text (None when it is no PNG or has none); chunks are read up to the image data."""
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89PNG\r\n\x1a\n":
            return None
        while len(head := fh.read(8)) == 8:
            size, kind = int.from_bytes(head[:4], "big"), head[4:]
            if kind in (b"IDAT", b"IEND") or size > 1 << 20:
                return None
            body = fh.read(size)
            fh.read(4)  # CRC
            if kind == b"tEXt" and body.startswith(b"Software\0"):
                return body[9:].decode("latin-1")
    return None


def written_here(path: Path) -> bool:
    """Whether an existing file may be overwritten: empty, or one that carries nmnet's mark."""
    try:
        if path.stat().st_size == 0:
            return True
        if path.suffix == ".mcap":
            from mcap.records import Header
            from mcap.stream_reader import StreamReader

            with open(path, "rb") as fh:
                first = next(iter(StreamReader(fh, skip_magic=False).records), None)
            return isinstance(first, Header) and first.library == LIBRARY
        if path.suffix == ".json":
            doc = json.loads(path.read_text())
            return isinstance(doc, dict) and str(doc.get("written_by", "")).startswith(LIBRARY)
        if path.suffix == ".png":
            return (_png_software(path) or "").startswith(LIBRARY)
        if path.suffix == ".md":
            return f"<!-- written by {LIBRARY}" in path.read_text()
        if path.suffix == ".pt" and zipfile.is_zipfile(path):  # torch.save's archive: the pickle is stored, not deflated
            with zipfile.ZipFile(path) as z:
                pickles = [z.read(n) for n in z.namelist() if n.endswith("data.pkl")]
            return any(b"written_by" in p and LIBRARY.encode() in p for p in pickles)
    except Exception:  # noqa: BLE001 - unreadable, or not the format its name says: not ours
        return False
    return False


def input_roots(inputs: Iterable[Path | None]) -> list[Path]:
    """The resolved inputs, and for a ROS 2 bag's data file (beside its ``metadata.yaml``) the bag's folder."""
    roots = []
    for p in inputs:
        if p is None or not Path(p).exists():
            continue
        r = Path(p).resolve()
        roots.append(r)
        if r.is_file() and (r.parent / "metadata.yaml").is_file():
            roots.append(r.parent)
    return roots


def _file_in_the_way(path: Path) -> Path | None:
    """The first folder on ``path``'s way that is a file (so the path cannot be made), or None."""
    return next((p for p in path.parents if p.exists() and not p.is_dir()), None)


def not_an_input(path: Path, flag: str, inputs: Iterable[Path | None]) -> None:
    """Refuse an output that is an input or lies inside an input folder (a bag's folder, a sequence folder)."""
    target = path.resolve()
    for root in input_roots(inputs):
        if target == root or root in target.parents:
            what = "is" if target == root else "lies inside"
            raise ValueError(f"{flag} {path} {what} an input of this command ({root}): nothing is written into an input; "
                             "choose a path outside it")


def not_a_folder(path: Path, flag: str, example: str) -> None:
    """Refuse a folder given as an output file, suggesting ``example`` in it."""
    if path.is_dir():
        raise ValueError(f"{flag} {path} is a folder: give a file name, e.g. {path / example}")


def not_someone_elses(path: Path, flag: str) -> None:
    """Refuse an existing file that nmnet did not write."""
    if path.is_file() and not written_here(path):
        raise FileExistsError(f"{flag} {path} exists and was not written by nmnet: it would be overwritten; choose "
                              "another path, or delete it first")


def output_file(path: Path | None, flag: str, example: str, inputs: Iterable[Path | None] = ()) -> None:
    """Before the work: refuse an output file that is a folder, an input or inside one, or a file nmnet did not
    write, and make its folder. Found only when the result is written, at the end of minutes of work, any of them
    would lose it (or a user's data). ``example``: a file name to suggest."""
    if path is None:
        return
    not_a_folder(path, flag, example)
    not_an_input(path, flag, inputs)
    not_someone_elses(path, flag)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        blocking = _file_in_the_way(path)
        why = f"{blocking} is a file, not a folder" if blocking is not None else f"cannot make its folder: {e.strerror or e}"
        raise ValueError(f"{flag} {path}: {why}") from e


def output_folder(path: Path | None, flag: str, what: str, inputs: Iterable[Path | None] = (),
                  names: Iterable[str] = ()) -> None:
    """Before the work: refuse a file given as an output folder, a path through a file (found when the first
    output is written, after the work, with only '[Errno 17] File exists'), an input folder or one inside it, and
    a folder holding a file of one of ``names`` (what the tool writes there) that nmnet did not write. The folder
    is made by its writer."""
    if path is None:
        return
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path} is a file: give a folder for {what}")
    if blocking := _file_in_the_way(path):
        raise ValueError(f"{flag} {path}: {blocking} is a file, not a folder")
    not_an_input(path, flag, inputs)
    for name in names:
        not_someone_elses(path / name, flag)


def replace_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """``write`` to a temporary file beside ``path``, then rename it there: an interrupted or failed write leaves the
    previous file (or none), never half a file. Each call has its own temporary name: a writer interrupted half-way
    (torch.save's zip writer, closed whenever it is collected) may still write into its file later, which must
    then not be the one renamed into place."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        write(tmp)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json(path: Path, doc: dict) -> None:
    """``doc`` as JSON with nmnet's mark (``written_by`` first); NaN and inf are written as null, which every JSON
    parser reads."""
    def clean(v):
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return None if isinstance(v, float) and not math.isfinite(v) else v

    text = json.dumps(clean({"written_by": written_by(), **doc}), indent=1, allow_nan=False)
    replace_atomically(path, lambda tmp: tmp.write_text(text))


def write_markdown(path: Path, text: str) -> None:
    """``text`` as a Markdown file, marked in a closing comment (invisible when rendered)."""
    text = f"{text.rstrip()}\n\n<!-- written by {written_by()} -->\n"
    replace_atomically(path, lambda tmp: tmp.write_text(text))


def save_figure(fig: Figure, path: Path) -> Path:
    """A matplotlib figure as a PNG at ``path`` (also without a .png suffix), marked; the figure is closed."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    replace_atomically(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png", metadata={"Software": written_by()}))
    plt.close(fig)
    return path


def save_image(path: Path, bgr: np.ndarray) -> Path:
    """A BGR (or mono) image as a marked PNG at ``path``."""
    import matplotlib.image

    rgb = bgr[..., ::-1] if bgr.ndim == 3 else bgr
    replace_atomically(path, lambda tmp: matplotlib.image.imsave(tmp, rgb, format="png", cmap="gray",
                                                                  metadata={"Software": written_by()}))
    return path
