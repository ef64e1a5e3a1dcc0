"""The coefficient set file's fields, documented; ``tests/docs/test_set_schema.py`` holds this table
to the sets canical writes (every field a set of any model kind, with every term kind, carries is
listed here, and every field listed here is one some set carries)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Field:
    path: str
    type: str
    meaning: str


INTRODUCTION = """\
`canical calibrate` writes one YAML file per axis (schema {schema}); `apply`, `serve`, `push`
and `export dcf` read it. Loading checks every field and the CRC: a damaged or hand-edited file
is refused with one line naming the problem. *raw* is the sensor's output as the session gives
it — the `raw` column of a CSV, or the DBC's physical value of the raw signal in a CAN log (its
scale and offset applied; for `canical.dbc` these are counts) — and ΔV = raw − `v0`."""

FIELDS: tuple[Field, ...] = (
    Field("schema", "integer", "file format version; a file of another schema is refused"),
    Field(
        "sensor.id",
        "string",
        "the sensor the set was calibrated for; on a canical IMU its serial number "
        "as decimal text (0x1018 sub 4), which `push` and the device check",
    ),
    Field("sensor.axis", "`x`, `y` or `z`", "the axis the set corrects"),
    Field("units.raw", "string", "unit of raw: the DBC signal's unit when calibrated from a CAN log, a "
          "session CSV's `# raw_units:` line, else `counts`; `serve` refuses a set whose unit is not its "
          "raw signal's (`counts` matches any)"),
    Field("units.rate", "string", "unit of the corrected rate (`deg/s`)"),
    Field("created", "ISO 8601 text", "when the set was written (UTC)"),
    Field("v0", "number", "zero bias in raw units, measured on the zero-rate plateaus"),
    Field(
        "model.kind",
        "`segmented-inverse`, `segmented-linear`, `forward-poly`",
        "the rate model (see [the three models](../science/models.md))",
    ),
    Field(
        "model.knots_raw",
        "list of numbers, ascending, inside the span",
        "segmented kinds: segment points in absolute raw units",
    ),
    Field(
        "model.segment_points_dps",
        "list of numbers",
        "segmented kinds: the same points as rates, informative",
    ),
    Field("model.scale", "positive number", "segmented kinds: u = ΔV / scale is the polynomials' variable"),
    Field(
        "model.coefficients",
        "list of lists (segmented) or list (forward-poly)",
        "segmented kinds: one row "
        "per segment, ω in ascending powers of u; forward-poly: ΔV in ascending powers of ω / rate_scale",
    ),
    Field(
        "model.smoothness",
        "`null`, `0` or `1`",
        "segmented kinds: joins free (`null`, the paper's), "
        "continuous (`0`, C0) or with equal slopes (`1`, C1)",
    ),
    Field(
        "model.span_raw",
        "[low, high]",
        "calibrated span in raw units; beyond it the rate is extrapolated linearly and flagged out of span",
    ),
    Field("model.out_of_span", "`linear-extrapolation`", "what happens beyond the span"),
    Field("model.rate_scale", "positive number", "forward-poly: ω / rate_scale is the polynomial's variable"),
    Field("model.rate_span_dps", "[low, high]", "forward-poly: rates the inversion searches"),
    Field("terms", "list", "effect terms of the closed loop (empty: the rate model alone); see below"),
    Field("terms[].kind", "`channel`, `time`, `direction`", "what the term's variable is"),
    Field("terms[].feature", "text", "the transform of the variable (table below)"),
    Field("terms[].form", "`bias` or `scale`", "ΔV' = ΔV − c·x (bias) or ΔV' = ΔV − c·x·ΔV (scale)"),
    Field("terms[].coefficient", "number", "c, the sensor's own sensitivity to x"),
    Field("terms[].channel", "text", "`channel` kind: the input's name (a CSV column, a configured input)"),
    Field("terms[].reference", "number", "the value of the variable where the term is zero"),
    Field("terms[].tau_s", "positive number",
          "time constant of a lag, derivative, warm-up or slope (and of a lag or derivative spline)"),
    Field(
        "terms[].threshold_raw",
        "positive number",
        "threshold of a direction tracker, or the knee of a gated term, in the units the feature names",
    ),
    Field("terms[].knots", "list of 2 to 64 increasing numbers",
          "`spline`, `rate_spline`, `lag_spline` and `derivative_spline` only: the segment ends of the "
          "piecewise cubic, of the channel, of ΔV in raw units, of the channel's lag or of its rate of "
          "change (flat beyond the ends)"),
    Field("terms[].pieces", "one list of 4 numbers per segment",
          "the spline features only: a0 a1 a2 a3 of a0 + a1·u + a2·u² + a3·u³ with u = its variable "
          "− the segment's first knot"),
    Field(
        "fit",
        "mapping",
        "statistics of the fit (samples, plateaus, training and held-out errors, the angle random walk "
        "`arw_deg_rt_h` that bias tracking tells a standstill by): "
        "not used to correct",
    ),
    Field("signature.key_id", "16 hex digits",
          "a signed set only (`canical sign`): the signer's key, the first 8 bytes of its public "
          "key's SHA-256"),
    Field("signature.version", "integer 0..2⁶³−1",
          "the set's version for its sensor: a daemon with `trust:` refuses one older than the set it runs"),
    Field("signature.sensor", "string", "the sensor the set was signed for (its `sensor.id`)"),
    Field("signature.ed25519", "base64 of 64 bytes",
          "the Ed25519 signature over the version, the sensor and the canonical JSON the CRC covers "
          "(see [signed sets](../signing.md))"),
    Field(
        "crc32",
        "`0x` and 8 hex digits",
        "CRC32 over the canonical JSON of everything else but a signature (sorted keys, "
        "no spaces); also the set's identifier on the bus; a signed set keeps the CRC it had unsigned",
    ),
)

TERMS_INTRODUCTION = """\
Effects act on the sensor's output, so a term corrects ΔV before the rate model: ΔV' = ΔV − c·x
(bias form) or ΔV' = ΔV − c·x·ΔV (scale form), then ω = f(ΔV'). The variable x by kind and feature:
`channel` — `offset` v − ref, `square` (v − ref)², `lag` the channel through a first-order lag τ,
`derivative` its rate of change smoothed over τ, `direction` the sign of its last significant
change (hysteresis), `gated` its level acting only beyond a knee in the output, `spline` a piecewise
cubic of it learned by the closed loop (`knots`, `pieces`; flat beyond the end knots),
`rate_spline` its level times a piecewise cubic of ΔV (a coefficient changing with rate; same
`knots`, `pieces`), `lag_spline` a piecewise cubic of its lag (τ) and `derivative_spline` one of its
rate of change smoothed over τ (same `knots`, `pieces`); `time` (input `time_s`, time since
power-on) — `warmup` 1 − exp(−t/τ), `linear` t;
`direction` (of the raw output) — `sign` its last significant rise or fall, `slope` its rate of
change. The kinds this canical accepts:"""

EXAMPLE_INTRO = "An example, written by `canical calibrate` (a simulated session, 3 segments, order 2):"


def example_text() -> str:
    """A real set, calibrated here from a simulated session (a fixed creation time: the page is stable)."""
    from dataclasses import replace

    from canical.calibration.pipeline import CalibrateOptions, calibrate
    from canical.sets import coefficient_file
    from canical.sim.sessions import paper_session

    session = paper_session(seed=3, dwell_s=3.0, sensor="4711", axis="z")
    options = CalibrateOptions(segments=3, order=2, extend=False)
    cset = calibrate(session, options, sensor_id="4711", axis="z").coefficients
    return coefficient_file.dumps(replace(cset, created="2026-01-01T00:00:00Z"))


def key_paths(content: Any, prefix: str = "") -> Iterator[str]:
    """Every field path of parsed set content, as the table writes them (``terms[].kind``);
    ``fit`` is one free-form mapping."""
    if isinstance(content, dict) and prefix != "fit":
        for key, value in content.items():
            path = f"{prefix}.{key}" if prefix else str(key)
            if isinstance(value, dict) and path != "fit":
                yield from key_paths(value, path)
            elif isinstance(value, list) and path == "terms":
                yield path
                for term in value:
                    yield from key_paths(term, "terms[]")
            else:
                yield path


def documented_paths() -> set[str]:
    return {f.path for f in FIELDS}
