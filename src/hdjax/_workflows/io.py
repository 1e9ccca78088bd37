"""Atomic output files: write to a temporary name in the same folder, then rename."""

import json
import math
import os
import pathlib
import tempfile


def _clean(obj):
    """JSON-ready copy: numpy/jax scalars to Python, NaN/inf to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if hasattr(obj, "tolist"):
        return _clean(obj.tolist())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    return obj


def _replace_atomically(path, suffix: str, write) -> pathlib.Path:
    """Create a temporary file (`suffix`) in `path`'s folder (created if needed), let
    `write(fd, tmp)` fill it, then rename it over `path`; on any error the temporary file is
    removed and the error raised, so `path` is either the old file or the whole new one."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    try:
        write(fd, tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path, text: str) -> pathlib.Path:
    """Write `text` (UTF-8, line ends as given) to `path`: a temporary file in the same folder,
    flushed to disk, then renamed over `path`. The folder is created if needed."""

    def write(fd, _tmp):
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    return _replace_atomically(path, ".tmp", write)


def atomic_write_json(path, obj) -> pathlib.Path:
    return atomic_write_text(path, json.dumps(_clean(obj), indent=2) + "\n")


def atomic_savefig(fig, path, **kwargs) -> pathlib.Path:
    """`fig.savefig` to `path` atomically (the temporary file keeps `path`'s suffix, which sets the format)."""

    def write(fd, tmp):
        os.close(fd)
        fig.savefig(tmp, **kwargs)

    return _replace_atomically(path, pathlib.Path(path).suffix, write)


def write_results(out, json_name: str, doc: dict, report: str, *, log=print) -> None:
    """A command's outputs in `out`: `json_name` (the JSON document `doc`, SPEC §3) and `report.md`,
    each written atomically, then one log line with `doc["timing_s"]["total"]` (s)."""
    out = pathlib.Path(out)
    atomic_write_json(out / json_name, doc)
    atomic_write_text(out / "report.md", report)
    log(f"wrote {out / json_name} and {out / 'report.md'} in {doc['timing_s']['total']:.1f} s")
