"""A progress bar for the tools' long loops (features, methods and pairs take minutes)."""

from __future__ import annotations

import sys
from collections.abc import Iterable


def progress(items: list, desc: str, unit: str) -> Iterable:
    """A progress bar on a terminal (none in a log) for the tools' long loops: features and methods take minutes."""
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit=unit, file=sys.stderr, disable=None, leave=False)
