"""Field-by-field differences between two compiled MuJoCo models, in words a person reads.

``tasks show`` prints them, and the shift-diff tests use them to check that a target model
differs from its base only where its effects say.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from offdyn_bench.json_values import is_number

# Row prefixes of MjModel array fields and the object type that names each row.
_ROW_OBJECTS: dict[str, mujoco.mjtObj] = {
    "body_": mujoco.mjtObj.mjOBJ_BODY,
    "jnt_": mujoco.mjtObj.mjOBJ_JOINT,
    "geom_": mujoco.mjtObj.mjOBJ_GEOM,
    "site_": mujoco.mjtObj.mjOBJ_SITE,
    "cam_": mujoco.mjtObj.mjOBJ_CAMERA,
    "actuator_": mujoco.mjtObj.mjOBJ_ACTUATOR,
    "pair_": mujoco.mjtObj.mjOBJ_PAIR,
    "tendon_": mujoco.mjtObj.mjOBJ_TENDON,
}

# Quantities the compiler derives from others (mj_setConst); they follow any physical change.
DERIVED_FIELDS = frozenset({
    "body_subtreemass", "body_invweight0", "dof_invweight0", "tendon_invweight0", "actuator_acc0",
    "actuator_length0", "dof_length", "actuator_lengthrange", "dof_M0", "cam_pos0", "cam_poscom0", "cam_mat0",
    "light_pos0", "light_poscom0", "light_dir0", "body_bvhadr", "bvh_aabb", "stat.meaninertia",
    "stat.meanmass", "stat.meansize", "stat.extent", "stat.center",
})


@dataclasses.dataclass(frozen=True)
class FieldDifference:
    """One changed field: which rows changed and their values before and after."""

    field: str
    rows: tuple[str, ...]
    before: np.ndarray
    after: np.ndarray

    @property
    def ratio(self) -> np.ndarray | None:
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.asarray(self.after, float) / np.asarray(self.before, float)
        return ratio if np.all(np.isfinite(ratio)) else None

    def describe(self) -> str:
        lines = []
        for row, before, after in zip(self.rows, self.before, self.after, strict=True):
            b = np.atleast_1d(before).astype(float)
            a = np.atleast_1d(after).astype(float)
            with np.errstate(divide="ignore", invalid="ignore"):
                r = a / b
            nonzero = b != 0
            uniform = nonzero.all() and np.allclose(r, r.flat[0])
            note = f"  (x{r.flat[0]:.4g})" if uniform else ""
            where = f"[{row}]" if row else ""
            lines.append(f"{self.field}{where}: {_fmt(b)} -> {_fmt(a)}{note}")
        return "\n".join(lines)


def _fmt(x: np.ndarray) -> str:
    if x.size == 1:
        return f"{x.item():.6g}"
    return "[" + " ".join(f"{v:.4g}" for v in x) + "]"


def _array_fields(obj: object, prefix: str = "") -> dict[str, np.ndarray]:
    out = {}
    for name in dir(obj):
        if name.startswith("_"):
            continue
        try:
            value = getattr(obj, name)
        except Exception:  # some attributes are only valid for certain model types
            continue
        if isinstance(value, np.ndarray) and value.dtype.kind in "fiub":
            out[prefix + name] = value
        elif is_number(value) and prefix:
            out[prefix + name] = np.array(value)
    return out


def model_fields(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Numeric fields of a compiled model, including ``opt.*`` and ``stat.*``."""
    fields = _array_fields(model)
    fields.update(_array_fields(model.opt, "opt."))
    fields.update(_array_fields(model.stat, "stat."))
    return fields


def _row_names(model: mujoco.MjModel, field: str, rows: np.ndarray) -> tuple[str, ...]:
    if field.startswith("dof_"):
        return tuple(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, model.dof_jntid[r]) or str(r) for r in rows)
    for prefix, objtype in _ROW_OBJECTS.items():
        if field.startswith(prefix):
            return tuple(mujoco.mj_id2name(model, objtype, int(r)) or f"#{r}" for r in rows)
    return tuple(str(r) for r in rows)


def model_differences(base: mujoco.MjModel, other: mujoco.MjModel, *, rtol: float = 1e-12,
                      include_derived: bool = False) -> list[FieldDifference]:
    """Every numeric field that differs between ``base`` and ``other`` (same structure)."""
    a, b = model_fields(base), model_fields(other)
    out = []
    for field in sorted(a):
        if field not in b or (not include_derived and field in DERIVED_FIELDS):
            continue
        x, y = a[field], b[field]
        if x.shape != y.shape:
            out.append(FieldDifference(field, ("shape",), np.array([x.shape]), np.array([y.shape])))
            continue
        if x.ndim == 0:
            if not np.isclose(x, y, rtol=rtol, atol=0):
                out.append(FieldDifference(field, ("",), x.reshape(1), y.reshape(1)))
            continue
        if x.size == 0:
            continue
        if "." in field:  # opt.gravity, stat.center: one vector, not rows of objects
            if not np.allclose(x, y, rtol=rtol, atol=0):
                out.append(FieldDifference(field, ("",), x.reshape(1, -1), y.reshape(1, -1)))
            continue
        rows_x = x.reshape(x.shape[0], -1)
        rows_y = y.reshape(y.shape[0], -1)
        changed = np.flatnonzero(~np.all(np.isclose(rows_x, rows_y, rtol=rtol, atol=0), axis=1))
        if changed.size:
            out.append(FieldDifference(field, _row_names(base, field, changed), rows_x[changed], rows_y[changed]))
    return out
