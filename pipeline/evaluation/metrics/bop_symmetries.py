"""Symmetry transformations of an object model, discretised as the BOP toolkit does.

BOP's ``models_info.json`` declares discrete symmetries as flattened 4x4 matrices
(translation in mm) and continuous ones as an axis and an offset (mm). MSSD and MSPD
take the minimum of their error over a finite set of symmetry transformations: the
identity, the discrete symmetries, and every continuous symmetry sampled with
``ceil(pi / max_sym_disc_step)`` rotations per turn, combined with each discrete one.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

import numpy as np

#: The BOP19 evaluation's ``max_sym_disc_step``.
DEFAULT_MAX_SYM_DISC_STEP = 0.01


def _continuous_rotations(
    axis: np.ndarray, offset: np.ndarray, max_sym_disc_step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Samples of one continuous symmetry: ``Rs (n, 3, 3)``, ``ts (n, 3)`` mm.

    The rotation about ``axis`` through the point ``offset`` maps x to
    ``R x - R offset + offset``. Sample 0 is the identity.
    """
    axis = np.asarray(axis, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(axis)
    if norm == 0:
        raise ValueError("continuous symmetry axis must be non-zero")
    # pi / step: the farthest vertex from the axis (at most one radius = half the
    # diameter away) moves at most step * diameter between consecutive samples.
    n = int(math.ceil(math.pi / max_sym_disc_step))
    angles = np.arange(n) * (2.0 * math.pi / n)
    # Imported here: scipy.spatial costs ~0.4 s at start-up, and most objects have no
    # continuous symmetry.
    from scipy.spatial.transform import Rotation

    Rs = Rotation.from_rotvec(angles[:, None] * (axis / norm)[None, :]).as_matrix()
    offset = np.asarray(offset, dtype=np.float64).reshape(3)
    ts = offset[None, :] - Rs @ offset
    return Rs, ts


def symmetry_transformations(
    symmetries_discrete: Iterable[Any] | None = None,
    symmetries_continuous: Iterable[Mapping[str, Any]] | None = None,
    max_sym_disc_step: float = DEFAULT_MAX_SYM_DISC_STEP,
) -> tuple[np.ndarray, np.ndarray]:
    """All symmetry transformations ``(R_s, t_s)`` of a model, identity included.

    symmetries_discrete: 4x4 matrices (or 16 values row-major), translation in mm.
    symmetries_continuous: dicts with ``axis`` (3,) and ``offset`` (3,) mm.
    Returns ``Rs (S, 3, 3)`` and ``ts (S, 3)`` float64 (mm), in the toolkit's order:
    for each discrete transformation (identity first), each continuous sample
    ``(Rc, tc)`` gives ``(Rc Rd, Rc td + tc)``. A pose ``(R, t)`` is equivalent to
    ``(R R_s, R t_s + t)``.
    """
    disc_R = [np.eye(3)]
    disc_t = [np.zeros(3)]
    for sym in symmetries_discrete or []:
        m = np.asarray(sym, dtype=np.float64).reshape(4, 4)
        disc_R.append(m[:3, :3])
        disc_t.append(m[:3, 3])
    dR = np.stack(disc_R)
    dt = np.stack(disc_t)

    cont = [
        _continuous_rotations(np.asarray(s["axis"]), np.asarray(s["offset"]), max_sym_disc_step)
        for s in (symmetries_continuous or [])
    ]
    if not cont:
        return dR, dt
    cR = np.concatenate([c[0] for c in cont])
    ct = np.concatenate([c[1] for c in cont])
    # Discrete-major order, as in the toolkit.
    Rs = np.einsum("cij,djk->dcik", cR, dR).reshape(-1, 3, 3)
    ts = (np.einsum("cij,dj->dci", cR, dt) + ct[None, :, :]).reshape(-1, 3)
    return Rs, ts


def model_symmetries(info: Any, max_sym_disc_step: float = DEFAULT_MAX_SYM_DISC_STEP) -> tuple[np.ndarray, np.ndarray]:
    """:func:`symmetry_transformations` of a ``ModelInfo``-like object or a dict.

    Reads ``symmetries_discrete`` / ``symmetries_continuous`` as attributes or keys
    (either may be absent).
    """
    if isinstance(info, Mapping):
        disc = info.get("symmetries_discrete")
        cont = info.get("symmetries_continuous")
    else:
        disc = getattr(info, "symmetries_discrete", None)
        cont = getattr(info, "symmetries_continuous", None)
    return symmetry_transformations(disc, cont, max_sym_disc_step)
