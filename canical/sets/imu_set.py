"""The IMU set: three single-axis sets and the coupling between the axes, one record, one CRC.

Why one record: the coupling is only right together with the three per-axis models it was
fitted on (their scales fix its diagonal), so they travel and are checked as one. Each axis is
the single-axis :class:`~canical.sets.coefficients.CoefficientSet`, unchanged; the file carries
``kind: imu-set`` at its top level (a single-axis file has no top-level ``kind``), the three
axes' content under ``axes``, the coupling matrix M (corrected = M @ per-axis corrected rates)
and its standard errors, and one ``crc32`` over everything, computed as
:mod:`canical.sets.coefficient_file` computes a set's. Loading checks the CRC, each axis as a
single-axis set is checked, and the coupling (3×3, finite, diagonal within 0.5..2, off-diagonal
≤ 10 %, not singular), and the coupled outputs are proven finite over the axes' spans.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml

from canical.errors import CanicalError
from canical.files.atomic_file import write_text_atomic
from canical.files.yaml_text import parse_yaml
from canical.sets import coefficient_file
from canical.sets.coefficients import SCHEMA_VERSION, CoefficientSet, finite
from canical.sets.finite_outputs import check_coupled_outputs, output_bound

IMU_SET_KIND = "imu-set"
AXES = ("x", "y", "z")
MAX_OFF_DIAGONAL = 0.10
MAX_CONDITION = 1e3
#: Bounds on each diagonal term. Why: each axis's own model already fixes that axis's scale
#: against the table's rate, so the coupling only mixes in the other axes: its diagonal is 1 up
#: to second-order terms of the (≤ 10 %) misalignment and the fit's error. A diagonal off by a
#: factor 2 rescales an axis already calibrated; a negative one flips it (−I), a tiny one zeroes
#: it (a turning vehicle reported standing), a huge one overflows (1e308·I): none is a coupling.
MIN_DIAGONAL = 0.5
MAX_DIAGONAL = 2.0

Matrix = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


def as_matrix(values: Any) -> Matrix:
    """A 3×3 nested tuple of floats from an array or nested lists."""
    m = np.asarray(values, dtype=float).reshape(3, 3)
    x, y, z = ((float(r[0]), float(r[1]), float(r[2])) for r in m)
    return (x, y, z)


@dataclass(frozen=True)
class ImuSet:
    """One IMU: the per-axis sets (x, y, z) and the coupling applied to their corrected rates."""

    sensor_id: str
    axes: tuple[CoefficientSet, CoefficientSet, CoefficientSet]
    coupling: Matrix
    coupling_se: Matrix
    fit: dict[str, Any] = field(default_factory=dict)
    created: str = ""
    schema: int = SCHEMA_VERSION

    def matrix(self) -> np.ndarray:
        return np.asarray(self.coupling, dtype=float)

    def to_dict(self) -> dict[str, Any]:
        """Plain content in file order (without the CRC, which covers it)."""
        return {
            "schema": self.schema,
            "kind": IMU_SET_KIND,
            "sensor": {"id": self.sensor_id},
            "created": self.created,
            "axes": {name: cset.to_dict() for name, cset in zip(AXES, self.axes, strict=True)},
            "coupling": {
                "applied_to": "per-axis corrected rates: corrected = matrix @ [x, y, z]",
                "matrix": [list(r) for r in self.coupling],
                "standard_errors": [list(r) for r in self.coupling_se],
            },
            "fit": self.fit,
        }


def imu_set_crc(imu: ImuSet) -> int:
    """The IMU set's CRC32 (its identifier), over the whole content."""
    return coefficient_file.content_crc(imu.to_dict())


def dumps(imu: ImuSet) -> str:
    """YAML text of an IMU set, CRC last."""
    content = imu.to_dict()
    content["crc32"] = f"0x{coefficient_file.content_crc(content):08x}"
    return yaml.safe_dump(content, sort_keys=False, default_flow_style=None, width=100)


def save(path: str | os.PathLike[str], imu: ImuSet) -> None:
    """Write an IMU set atomically (validated first, so no bad set is ever written)."""
    text = dumps(imu)
    loads(text, str(path))
    write_text_atomic(path, text)


def is_imu_set_file(path: str | os.PathLike[str]) -> bool:
    """Whether a set file is an IMU set (a top-level ``kind: imu-set`` line), without parsing it.

    A single-axis set has no top-level ``kind``; an unreadable file is not one (its loader says why).
    """
    try:
        with open(path, encoding="utf-8") as handle:
            return any(line.rstrip() == f"kind: {IMU_SET_KIND}" for line in handle)
    except (OSError, UnicodeDecodeError):
        return False


def load(path: str | os.PathLike[str]) -> ImuSet:
    return loads(coefficient_file.read_text(path, "IMU set file"), str(path))


def loads(text: str, source: str = "<imu set>") -> ImuSet:
    """Parse and fully validate an IMU set; any defect raises one :class:`CanicalError` line."""
    return from_content(parse_yaml(text, source), source)


def from_content(content: Any, source: str) -> ImuSet:
    """Validate parsed content and build the IMU set."""

    def fail(msg: str) -> CanicalError:
        return CanicalError(f"{source}: {msg}")

    if not isinstance(content, dict):
        raise fail("not an IMU set (expected a mapping at the top level)")
    if content.get("kind") != IMU_SET_KIND:
        raise fail("a single-axis coefficient set, not an IMU set (no 'kind: imu-set')")
    if content.get("schema") != SCHEMA_VERSION:
        raise fail(f"schema {content.get('schema')!r} not supported "
                   f"(this canical reads schema {SCHEMA_VERSION})")
    _check_crc(content, fail)
    sensor = content.get("sensor")
    if not isinstance(sensor, dict) or not isinstance(sensor.get("id"), str) or not sensor["id"]:
        raise fail("sensor.id must be a non-empty string")
    axes = content.get("axes")
    if not isinstance(axes, dict) or sorted(axes) != sorted(AXES):
        raise fail("axes must be a mapping with exactly x, y and z")
    sets = tuple(_axis_set(axes[name], name, source) for name in AXES)
    coupling = content.get("coupling")
    if not isinstance(coupling, dict):
        raise fail("coupling missing or not a mapping")
    matrix = _matrix(coupling.get("matrix"), "coupling.matrix", fail)
    errors = _matrix(coupling.get("standard_errors"), "coupling.standard_errors", fail)
    check_coupling(np.asarray(matrix), source)
    _check_standard_errors(errors, fail)
    _check_coupled_outputs(np.asarray(matrix), sets, fail)
    fit = content.get("fit", {})
    if not isinstance(fit, dict):
        raise fail("fit must be a mapping")
    return ImuSet(sensor["id"], (sets[0], sets[1], sets[2]), matrix, errors, fit,
                  str(content.get("created", "")))


def _check_crc(content: dict[str, Any], fail: coefficient_file.FailFn) -> None:
    crc_text = content.get("crc32")
    if not isinstance(crc_text, str):
        raise fail("crc32 missing")
    try:
        crc = int(crc_text, 16)
    except ValueError:
        raise fail(f"crc32 {crc_text!r} is not hexadecimal") from None
    try:
        actual = coefficient_file.content_crc(content)
    except (TypeError, ValueError) as exc:
        raise fail(f"content cannot be checked ({exc})") from None
    if crc != actual:
        raise fail(f"CRC mismatch (file says 0x{crc:08x}, content gives 0x{actual:08x}): damaged or edited")


def _axis_set(content: Any, name: str, source: str) -> CoefficientSet:
    """One axis checked as a single-axis set is (the whole file's CRC already covers it)."""
    if not isinstance(content, dict):
        raise CanicalError(f"{source}: axes.{name} must be a mapping")
    checked = {**content, "crc32": f"0x{coefficient_file.content_crc(content):08x}"}
    cset = coefficient_file.from_content(checked, f"{source}: axes.{name}")
    if cset.axis != name:
        raise CanicalError(f"{source}: axes.{name} is a set for axis {cset.axis}")
    return cset


def _matrix(value: Any, key: str, fail: coefficient_file.FailFn) -> Matrix:
    ok = (isinstance(value, list) and len(value) == 3
          and all(isinstance(r, list) and len(r) == 3 and all(finite(v) for v in r) for r in value))
    if not ok:
        raise fail(f"{key} must be 3 rows of 3 finite numbers")
    return as_matrix(value)


def check_coupling(matrix: np.ndarray, source: str) -> None:
    """Refuse, in one line, a coupling whose diagonal is outside :data:`MIN_DIAGONAL` ..
    :data:`MAX_DIAGONAL`, that is singular, or that has an off-diagonal term above 10 %.

    Why near identity: the coupling corrects how far an axis is mounted askew, after each axis's
    own model fixed its scale (see :data:`MIN_DIAGONAL`). With the diagonal in 0.5..2 and the
    off-diagonal terms within 10 % the matrix is diagonally dominant, so never singular; the
    condition check stays as the device's rule too."""
    m = np.asarray(matrix, dtype=float)
    diagonal = np.diag(m)
    _check_diagonal(diagonal, source)
    with np.errstate(all="ignore"):
        cond = float(np.linalg.cond(m))
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise CanicalError(f"{source}: the coupling matrix is singular (condition {cond:.3g})")
    off = np.abs(m - np.diag(diagonal))
    if off.max() > MAX_OFF_DIAGONAL:
        i, j = np.unravel_index(int(np.argmax(off)), off.shape)
        raise CanicalError(f"{source}: coupling term {AXES[i]}{AXES[j]} is {100 * m[i, j]:+.1f} %, above "
                           f"{100 * MAX_OFF_DIAGONAL:g} %: an axis mislabelled or mounted askew")


def _check_diagonal(diagonal: np.ndarray, source: str) -> None:
    """Each diagonal term within :data:`MIN_DIAGONAL` .. :data:`MAX_DIAGONAL` (NaN fails too)."""
    for name, d in zip(AXES, diagonal.tolist(), strict=True):
        if not MIN_DIAGONAL <= d <= MAX_DIAGONAL:
            raise CanicalError(f"{source}: coupling term {name}{name} is {d:.6g}, outside "
                               f"{MIN_DIAGONAL:g}..{MAX_DIAGONAL:g}: the coupling must be near identity "
                               f"(each axis's own model fixes its scale); recalibrate the IMU")


def _check_standard_errors(errors: Matrix, fail: coefficient_file.FailFn) -> None:
    """A standard error is a spread: never negative."""
    if any(v < 0 for row in errors for v in row):
        raise fail("coupling.standard_errors must not be negative")


def _check_coupled_outputs(matrix: np.ndarray, sets: tuple[CoefficientSet, ...],
                           fail: coefficient_file.FailFn) -> None:
    """The finite-outputs proof through the coupling: each axis's bound, then the product's."""
    bounds = []
    for cset in sets:
        lo, hi = cset.span_raw
        bound, _ = output_bound(cset.rate_model(), cset.terms, (lo - cset.v0, hi - cset.v0))
        bounds.append(bound)
    unbounded = check_coupled_outputs(matrix, (bounds[0], bounds[1], bounds[2]))
    if unbounded is not None:
        raise fail(unbounded.message())
