"""Files written whole or not at all: a reader never sees half a file."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

__all__ = ["write_atomically", "write_text", "write_json"]


def write_atomically(path: Path, content: bytes) -> None:
    """Write ``content`` to a hidden temporary file beside ``path``, then rename it into place."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(content)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def write_text(output: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``output`` atomically, making its folder."""
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(output, text.encode())
    return output


def write_json(output: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    return write_text(output, json.dumps(data, indent=2) + "\n")
