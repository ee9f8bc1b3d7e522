"""Pose estimates in the BOP results CSV format.

``scene_id,im_id,obj_id,score,R,t,time`` with one estimate per line; R is 9
space-separated values (row-major), t 3 values in mm, time the wall time spent on the
whole image in seconds (-1 if unknown). The BOP toolkit requires the same time on
every line of an image, which ``write_results_csv`` checks.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Mapping

import numpy as np

from .errors import BopFormatError
from pipeline.common.store import atomic_write_text

from .jsonio import brief, load_json, read_text

if TYPE_CHECKING:  # pandas (0.2 s) is imported where a DataFrame is made: most jobs never do
    import pandas as pd

HEADER = "scene_id,im_id,obj_id,score,R,t,time"
COLUMNS = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
# Ids are stored as int64 columns; a larger value is a corrupt file, not an id.
_INT64_MIN, _INT64_MAX = -(2 ** 63), 2 ** 63 - 1


def _int64(value: int) -> int:
    """``value`` if it fits the int64 id columns, else ValueError."""
    if not _INT64_MIN <= value <= _INT64_MAX:
        raise ValueError(f"{value} does not fit in int64")
    return value


def _parse_int(raw: str) -> int:
    """An int64 id from a CSV field."""
    try:
        value = int(raw)
    except ValueError:  # not an integer, or beyond Python's 4300-digit limit
        raise ValueError("expected an integer") from None
    return _int64(value)


def _json_finite(value: Any) -> float | None:
    """``value`` as a float if it is a finite JSON number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        f = float(value)
    except OverflowError:  # an int beyond the float range (JSON allows any digits)
        return None
    return f if math.isfinite(f) else None


def _parse_finite(raw: str) -> float:
    """A finite float from a CSV field (score, time: NaN would break ranking and timing)."""
    value = float(raw)
    if not math.isfinite(value):
        raise ValueError("non-finite value")
    return value


def _rows(rows: pd.DataFrame | Iterable[Mapping[str, Any]]) -> Iterable[Mapping[str, Any]]:
    import pandas as pd

    if isinstance(rows, pd.DataFrame):
        return (r for _, r in rows.iterrows())
    return rows


def _num(x: float) -> str:
    # repr of a Python float is the shortest exact form, so reading back is lossless.
    return repr(float(x))


def write_results_csv(path: Path | str, rows: pd.DataFrame | Iterable[Mapping[str, Any]]) -> None:
    """Write estimates (DataFrame or dicts with scene_id, im_id, obj_id, score, R (3, 3), t (3,) mm, time s).

    ``time`` may be omitted (written as -1). Raises ValueError on a bad shape,
    a non-finite value, or an image whose lines disagree on time.
    """
    lines = [HEADER]
    times: dict[tuple[int, int], float] = {}
    for i, r in enumerate(_rows(rows)):
        try:
            R = np.asarray(r["R"], dtype=np.float64).reshape(9)
            t = np.asarray(r["t"], dtype=np.float64).reshape(3)
            scene_id, im_id, obj_id = int(r["scene_id"]), int(r["im_id"]), int(r["obj_id"])
            score = float(r["score"])
        except (KeyError, ValueError, TypeError) as e:
            raise ValueError(f"write_results_csv({path}): row {i}: {e!r}") from None
        time = r.get("time", -1.0) if hasattr(r, "get") else -1.0
        time = -1.0 if time is None or (isinstance(time, float) and math.isnan(time)) else float(time)
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and math.isfinite(score) and math.isfinite(time)):
            raise ValueError(f"write_results_csv({path}): row {i}: non-finite score, R, t or time")
        key = (scene_id, im_id)
        if times.setdefault(key, time) != time:
            raise ValueError(
                f"write_results_csv({path}): row {i}: time {time} differs from {times[key]} given earlier for "
                f"scene {scene_id} image {im_id}; BOP needs one time per image"
            )
        lines.append(
            f"{scene_id},{im_id},{obj_id},{_num(score)},{' '.join(map(_num, R))},{' '.join(map(_num, t))},{_num(time)}"
        )
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_results_csv(path: Path | str) -> pd.DataFrame:
    """Read a BOP results CSV into a DataFrame.

    Columns: scene_id, im_id, obj_id (int64), score (float64), R (object: (3, 3)
    float64 arrays), t (object: (3,) float64 mm), time (float64 s; -1 when the file has
    no time column). The file must be UTF-8 text (a leading BOM is accepted); ids must
    fit in int64 and score, R, t and time be finite. Anything else raises
    ``BopFormatError`` naming the file, the line number and the field, on one line.
    """
    path = Path(path)
    text = read_text(path)  # UTF-8 (a BOM allowed), else one line saying it is not UTF-8 text
    lines = text.splitlines()
    if not lines:
        raise BopFormatError(f"{path}: empty file (expected header '{HEADER}')")
    header = [h.strip() for h in lines[0].split(",")]
    if header not in (COLUMNS, COLUMNS[:-1]):
        raise BopFormatError(f"{path}: line 1: header must be '{HEADER}' (time optional), got {brief(lines[0])}")
    has_time = len(header) == 7
    records: dict[str, list] = {c: [] for c in COLUMNS}
    for lineno, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(",")
        if len(parts) != len(header):
            raise BopFormatError(f"{path}: line {lineno}: expected {len(header)} comma-separated fields, got {len(parts)}")

        def field(name: str, parse, n: int | None = None):
            raw = parts[header.index(name)].strip()
            try:
                if n is None:
                    value = parse(raw)
                else:
                    value = np.array([float(v) for v in raw.split()], dtype=np.float64)
                    if value.size != n:
                        raise ValueError(f"expected {n} values, got {value.size}")
                    if not np.all(np.isfinite(value)):
                        raise ValueError("non-finite value")
            except ValueError as e:
                raise BopFormatError(f"{path}: line {lineno}, field '{name}': {e} (got {brief(raw)})") from None
            return value

        records["scene_id"].append(field("scene_id", _parse_int))
        records["im_id"].append(field("im_id", _parse_int))
        records["obj_id"].append(field("obj_id", _parse_int))
        records["score"].append(field("score", _parse_finite))
        records["R"].append(field("R", None, 9).reshape(3, 3))
        records["t"].append(field("t", None, 3))
        records["time"].append(field("time", _parse_finite) if has_time else -1.0)
    import pandas as pd

    df = pd.DataFrame(
        {
            "scene_id": pd.Series(records["scene_id"], dtype="int64"),
            "im_id": pd.Series(records["im_id"], dtype="int64"),
            "obj_id": pd.Series(records["obj_id"], dtype="int64"),
            "score": pd.Series(records["score"], dtype="float64"),
            "R": pd.Series(records["R"], dtype=object),
            "t": pd.Series(records["t"], dtype=object),
            "time": pd.Series(records["time"], dtype="float64"),
        }
    )
    return df


def read_estimates_json(path: Path | str) -> pd.DataFrame:
    """Estimates stored as a JSON list of {scene_id, im_id, obj_id, score, cam_R_m2c, cam_t_m2c[, time]}.

    Same columns as ``read_results_csv`` (used by the estimate files shipped with the
    shared test data). cam_R_m2c is 9 numbers (row-major), cam_t_m2c 3 (mm); ids are
    integers (integral floats allowed) fitting in int64; score and time finite numbers
    (time absent or null: -1). Errors name the file, the entry index and the field.
    """
    path = Path(path)
    content = load_json(path)
    if not isinstance(content, list):
        raise BopFormatError(f"{path}: expected a JSON list of estimates, got {type(content).__name__}")
    rows = []
    for i, d in enumerate(content):
        if not isinstance(d, dict):
            raise BopFormatError(f"{path}: entry {i}: expected an object, got {type(d).__name__}")

        def bad(name: str, msg: str) -> BopFormatError:
            return BopFormatError(f"{path}: entry {i}, field '{name}': {msg}")

        for k in ("scene_id", "im_id", "obj_id", "score", "cam_R_m2c", "cam_t_m2c"):
            if k not in d:
                raise bad(k, "missing")
        row: dict[str, Any] = {}
        for k in ("scene_id", "im_id", "obj_id"):
            v = d[k]
            # JSON writers may emit integral floats (3.0); bools are not ids.
            if isinstance(v, bool) or not (isinstance(v, int) or (isinstance(v, float) and v.is_integer())):
                raise bad(k, f"expected an integer, got {brief(v)}")
            try:
                row[k] = _int64(int(v))
            except ValueError as e:
                raise bad(k, str(e)) from None
        time = d.get("time", -1.0)
        for k, v in (("score", d["score"]), ("time", -1.0 if time is None else time)):
            number = _json_finite(v)
            if number is None:
                raise bad(k, f"expected a finite number, got {brief(v)}")
            row[k] = number
        for k, out, n in (("cam_R_m2c", "R", 9), ("cam_t_m2c", "t", 3)):
            v = d[k]
            values = [_json_finite(x) for x in v] if isinstance(v, list) else []
            if len(values) != n or None in values:
                raise bad(k, f"expected {n} finite numbers, got {brief(v)}")
            row[out] = np.array(values, dtype=np.float64).reshape((3, 3) if n == 9 else (3,))
        rows.append(row)
    import pandas as pd

    df = pd.DataFrame(rows, columns=COLUMNS)
    return df.astype({"scene_id": "int64", "im_id": "int64", "obj_id": "int64", "score": "float64", "time": "float64"})


def image_times(stage_times: Iterable[pd.DataFrame], prior_time: pd.Series | None = None) -> pd.Series:
    """BOP's time per image (s), indexed by (scene_id, im_id): the sum of the per-image
    times of the scene-side stages (tables with scene_id, im_id, time_s), plus the
    localisation prior's own time for the image (``prior_time``, negative = unknown = 0).
    Model onboarding is excluded, as BOP defines it."""
    import pandas as pd

    frames = [t[["scene_id", "im_id", "time_s"]] for t in stage_times]
    per_image = pd.concat(frames, ignore_index=True).groupby(["scene_id", "im_id"]).time_s.sum()
    if prior_time is not None:
        per_image = per_image.add(prior_time.clip(lower=0.0), fill_value=0.0)
    return per_image


def estimates_rows(poses: pd.DataFrame, per_image: pd.Series) -> list[dict[str, Any]]:
    """Rows for :func:`write_results_csv` from estimates (scene_id, im_id, obj_id, score,
    R as 9 floats, t mm) and the time of each image (:func:`image_times`)."""
    return [{"scene_id": r.scene_id, "im_id": r.im_id, "obj_id": r.obj_id, "score": r.score,
             "R": np.asarray(r.R).reshape(3, 3), "t": np.asarray(r.t), "time": float(per_image.loc[(r.scene_id, r.im_id)])}
            for r in poses.itertuples(index=False)]
