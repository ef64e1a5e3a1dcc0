"""Cost of the firmware evaluator (firmware/canical_eval.c) per sample, here and on a Cortex-M4F.

Prints, for a set of every model kind, one with every term kind, one with a spline term (8 and 64
knots), and for an IMU set (three axes and their coupling, ``ce_eval3``: each axis's set, then
corrected = M @ the three rates):

* nanoseconds per sample of the C library on this machine (``ce_eval_block`` over 1,000,000
  samples through ctypes, -O2; best of 5), beside canical's Python evaluator per sample
  (``Corrector.correct_one``) for scale;
* floating-point operations per sample (add, subtract, multiply, divide, compare, int/float
  conversion), counted from the source along the path each sample takes (inside the span,
  beyond it, and the worst case the library's limits allow);
* for the spline rows, the largest difference from ``canical apply`` (Corrector) over the samples
  timed; for the IMU set rows, from ``canical apply imu.yaml`` (ImuCorrector);
* with ``arm-none-eabi-gcc`` (Debian ``gcc-arm-none-eabi``): code size of a Cortex-M4F build
  (-mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard, freestanding) at -O2 and -Os, and of
  the functions a sample runs through.

    python tests/benchmarks/bench_firmware_eval.py [--samples N] [--quick]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from support.firmware_cases import (
    MODELS,
    TERMS,
    imu_set_of,
    imu_stream,
    model_set,
    saturating_spline,
    stream,
    term_set,
    with_terms_dicts,
)

from canical.device.firmware_eval import FirmwareCorrector, FirmwareImuCorrector
from canical.sets import term_kinds
from canical.sets.corrector import Corrector
from canical.sets.imu_corrector import ImuCorrector
from canical.sets.term_kinds import TermKind

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"
M4_FLAGS = ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16", "-ffreestanding",
            "-std=c99", "-Wall", "-Wextra", "-Werror"]  # fmt: skip
PER_SAMPLE = (
    "ce_eval",
    "ce_eval.part.0",
    "forward_rate",
    "expm1_f",
    "horner",
    "horner_slope",
    "term_feature",
    "hysteresis",
    "pair_add",
    "channel_lag_gap",
)
LIMITS = {"segments": 16, "coeffs": 10, "terms": 16, "newton": 40, "spline_knots": 64}
COUPLING_OPS = 18  # per axis r + (d0 r0 + d1 r1 + d2 r2): three multiplies, three adds

# Operations counted from canical_eval.c along each path (see firmware/README.md, "Cost per
# sample"): float add, subtract, multiply, divide, negate, compare and int<->float conversion
# each count one; integer arithmetic is not counted.
EXPM1 = 29  # checks 3, range reduction 10, degree-7 polynomial 13, scaling 3
# A channel's lag y after its first τ (the costlier branch; the running mean before it is 16):
# dt 2, exp argument 2, expm1, negate 1, step 3, float-pair add 10, gap 2.
LAG_GAP = 20 + EXPM1
# A gated level beyond its knee (the costlier branch): |dv| 2, the knee compare 1, v - ref 1,
# |dv| - knee 1, divide 1, multiply 1.
# A spline inside its knots: the two clamp tests 4, the binary search 2 per step (log2 of the
# segments, rounded up: 6 for 64 knots), u 2, Horner 6; counted at the most knots a spline may have.
SPLINE = 4 + 2 * 6 + 2 + 6
TERM_OPS: dict[TermKind, int] = {
    term_kinds.CHANNEL_OFFSET: 1, term_kinds.CHANNEL_SQUARE: 2, term_kinds.TIME_WARMUP: 3 + EXPM1,
    term_kinds.TIME_LINEAR: 0, term_kinds.DIRECTION_SIGN: 8, term_kinds.DIRECTION_SLOPE: 10 + EXPM1,
    term_kinds.CHANNEL_LAG: LAG_GAP + 2, term_kinds.CHANNEL_DERIVATIVE: LAG_GAP + 1,
    term_kinds.CHANNEL_DIRECTION: 8, term_kinds.CHANNEL_GATED: 7, term_kinds.CHANNEL_SPLINE: SPLINE,
    term_kinds.CHANNEL_RATE_SPLINE: SPLINE + 2,  # then (v - ref) and the product
    term_kinds.CHANNEL_LAG_SPLINE: LAG_GAP + 1 + SPLINE,  # the lag v - gap, then S of it
    term_kinds.CHANNEL_DERIVATIVE_SPLINE: LAG_GAP + 1 + SPLINE,  # the gap times 1/τ, then S of it
}  # fmt: skip
# kinds the C evaluator refuses (c_name None) have no cost there
_UNCOUNTED = [k for k in term_kinds.ALL if k.c_name is not None and k not in TERM_OPS]
if _UNCOUNTED:  # a kind added to the registry needs its count here (the quick-mode test runs this)
    raise SystemExit(f"bench_firmware_eval: no operation count for {', '.join(map(repr, _UNCOUNTED))}")


def operations(segments: int, coeffs: int, features: list[TermKind], scale_terms: int) -> tuple[int, int]:
    """Piecewise model: (inside the span, beyond it) for one sample, worst segment."""
    base = 4 + 6  # dV and time in seconds; the two span decisions (two subtractions, a compare)
    terms = sum(TERM_OPS[f] + 2 for f in features) + scale_terms  # feature, then c*x (*dV) added
    poly = 2 + 2 * (coeffs - 1)  # t = (dV' - mid) * (1/half) of the segment, then Horner
    inside = base + terms + 2 + 3 * (segments - 1) + poly  # segment search: 3 per segment point
    beyond = base + terms + 1 + poly + 4 * coeffs - 2  # slope at the edge, linear extrapolation
    return inside, beyond


def forward_operations(coeffs: int, newton: int) -> tuple[int, int]:
    """Forward polynomial: (inside, beyond) for ``newton`` Newton steps from the chord."""
    inside = 12 + 3 + newton * (4 * (coeffs - 1) + 11) + 1
    return inside, inside + 4 * coeffs - 1


def imu_rows(cases: dict) -> list[tuple[str, object, tuple[int, int]]]:
    """The IMU-set rows: a three-axis sample with coupling, each axis a segmented-inverse set
    without terms (what `canical calibrate x.csv y.csv z.csv` writes) and with every term."""
    plain = cases["segmented-inverse"]
    segments, coeffs = len(plain.model.coefficients), len(plain.model.coefficients[0])
    every = cases["segmented-inverse + every term"]
    terms = list(every.terms)
    rows = []
    for name, cset, features, scale in (("IMU set: 3 x segmented-inverse + M", plain, [], 0),
                                        ("IMU set: 3 x every term + M", every, [t.spec for t in terms],
                                         sum(t.form == "scale" for t in terms))):
        inside, beyond = operations(segments, coeffs, features, scale)
        rows.append((name, cset, (3 * inside + COUPLING_OPS, 3 * beyond + COUPLING_OPS)))
    return rows


def best_of(fn, repeats: int = 5) -> float:
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_000_000)
    parser.add_argument("--quick", action="store_true", help="a few samples, one timing run, no ARM build "
                        "(checks that the script works; figures meaningless)")
    args = parser.parse_args()
    repeats = 1 if args.quick else 5
    if args.quick:
        args.samples = min(args.samples, 2_000)
    cases = {m: model_set(m) for m in MODELS}
    cases["segmented-inverse + every term"] = term_set(tuple(TERMS))
    plain = cases["segmented-inverse"]
    cases["segmented-inverse + 8-knot spline"] = term_set(("channel-spline",))
    knots64 = np.linspace(4.05, 46.05, LIMITS["spline_knots"]).tolist()
    cases["segmented-inverse + 64-knot spline"] = with_terms_dicts(plain, (saturating_spline(knots64),))
    spline_agreement = []
    print(f"C evaluator on this machine: ns per sample over {args.samples:,} samples (best of {repeats})")
    head = f"{'set':34s} {'segs':>4s} {'coef':>4s} {'C ns':>7s} {'Python µs/sample':>17s}"
    print(f"{head} {'ops in/out of span':>19s}")
    for name, cset in cases.items():
        raw, inputs = stream(cset, args.samples)
        fw = FirmwareCorrector(cset)
        c_s = best_of(lambda fw=fw, raw=raw, inputs=inputs: fw.correct(raw, inputs), repeats)
        c_ns = c_s / args.samples * 1e9
        py = Corrector(cset)
        rows = [{k: float(v[i]) for k, v in inputs.items()} for i in range(min(20_000, args.samples))]

        def python(py=py, rows=rows, raw=raw):
            return [py.correct_one(raw[i], r) for i, r in enumerate(rows)]

        py_us = best_of(python, min(repeats, 3)) / len(rows) * 1e6
        terms = list(cset.terms)
        if not cset.kind.piecewise:
            coeffs, segments = len(cset.model.coefficients), 1
            ops = forward_operations(coeffs, 3)
        else:
            segments, coeffs = len(cset.model.coefficients), len(cset.model.coefficients[0])
            ops = operations(
                segments, coeffs, [t.spec for t in terms], sum(t.form == "scale" for t in terms)
            )
        print(f"{name:34s} {segments:4d} {coeffs:4d} {c_ns:7.1f} {py_us:17.2f} {ops[0]:9d} / {ops[1]:<7d}")
        if "spline" in name:
            expected, flags = Corrector(cset).correct(raw, inputs)
            rate, oos = fw.correct(raw, inputs)
            spline_agreement.append((float(np.max(np.abs(rate - expected))), int(np.sum(oos != flags))))
    largest = " / ".join(f"{d:.1e}" for d, _ in spline_agreement)
    differing = " / ".join(str(f) for _, f in spline_agreement)
    print(f"spline rows (a bias of 60·tanh((T − 25)/10) counts) against `canical apply` over "
          f"{args.samples:,} samples: largest difference {largest} deg/s, out-of-span flags differing "
          f"{differing}")
    print("(spline operations counted at 64 knots: 6 binary-search steps; 8 knots take 3)")
    agreement = []
    for name, cset, ops in imu_rows(cases):
        imu = imu_set_of(cset)
        raw, inputs = imu_stream(imu, args.samples)
        fw3 = FirmwareImuCorrector(imu)
        c_s = best_of(lambda fw3=fw3, raw=raw, inputs=inputs: fw3.correct(raw, inputs), repeats)
        c_ns = c_s / args.samples
        py3 = [Corrector(c) for c in imu.axes]
        m = imu.coupling
        n_py = min(20_000, args.samples)
        rows3 = [{k: float(v[i]) for k, v in inputs.items()} for i in range(n_py)]

        def python3(py3=py3, rows3=rows3, raw=raw, m=m):
            for i, r in enumerate(rows3):
                per = [c.correct_one(raw[i, k], r)[0] for k, c in enumerate(py3)]
                [m[j][0] * per[0] + m[j][1] * per[1] + m[j][2] * per[2] for j in range(3)]

        py_us = best_of(python3, min(repeats, 3)) / n_py * 1e6
        print(f"{name:34s} {'':4s} {'':4s} {c_ns * 1e9:7.1f} {py_us:17.2f} {ops[0]:9d} / {ops[1]:<7d}")
        expected, flags = ImuCorrector(imu).correct(raw, inputs)
        rates, oos = fw3.correct(raw, inputs)
        agreement.append((float(np.max(np.abs(rates - expected))), int(np.sum(oos != flags))))
    print("(three axes: ns per three-axis sample, ce_eval3_block; operations those of the three sets plus")
    print(f" the coupling's {COUPLING_OPS})")
    print(f"IMU set rows against `canical apply imu.yaml` (ImuCorrector) over {args.samples:,} samples: "
          "largest difference " + " / ".join(f"{d:.1e}" for d, _ in agreement) + " deg/s, out-of-span "
          "flags differing " + " / ".join(str(f) for _, f in agreement))
    lags = [term_kinds.CHANNEL_LAG] * LIMITS["terms"]
    worst = operations(LIMITS["segments"], LIMITS["coeffs"], lags, LIMITS["terms"])
    fwd = forward_operations(LIMITS["coeffs"], LIMITS["newton"])
    print(
        f"worst case the limits allow: piecewise {max(worst)} operations (16 segments, order 9, "
        f"{LIMITS['terms']} lag terms), forward polynomial {max(fwd)} (order 9, 40 Newton steps)"
    )
    print("(forward polynomial counted with 3 Newton steps from the chord; a counting build measured 2.2 on")
    print(" average over this stream, out-of-span samples included)")

    cc = shutil.which("arm-none-eabi-gcc")
    if args.quick:
        return
    if cc is None:
        print("\nCortex-M4F: no arm-none-eabi-gcc here (apt-get install gcc-arm-none-eabi)")
        return
    version = subprocess.run([cc, "--version"], capture_output=True, text=True).stdout.splitlines()[0]
    print(f"\nCortex-M4F build ({version}), canical_eval.c alone (no C library needed):")
    with tempfile.TemporaryDirectory() as tmp:
        for opt in ("-O2", "-Os"):
            obj = Path(tmp) / f"ce{opt}.o"
            subprocess.run(
                [cc, *M4_FLAGS, opt, "-c", "-o", str(obj), str(FIRMWARE / "canical_eval.c")], check=True
            )
            size = subprocess.run(["arm-none-eabi-size", str(obj)], capture_output=True, text=True).stdout
            text = int(size.splitlines()[1].split()[0])
            syms = subprocess.run(["arm-none-eabi-nm", "-S", "--size-sort", str(obj)], capture_output=True,
                                  text=True).stdout.splitlines()  # fmt: skip
            sizes = {ln.split()[-1]: int(ln.split()[1], 16) for ln in syms if len(ln.split()) == 4}
            path = sum(v for k, v in sizes.items() if k in PER_SAMPLE)
            undefined = subprocess.run(
                ["arm-none-eabi-nm", "-u", str(obj)], capture_output=True, text=True
            ).stdout
            soft = sorted({ln.split()[-1] for ln in undefined.splitlines() if ln.strip()})
            print(
                f"  {opt}: text {text} bytes (data 0, bss 0); per-sample functions {path} bytes; "
                f"ce_load {sizes.get('ce_load', 0)} bytes"
            )
        print(f"  external symbols: {', '.join(soft)} (libgcc's software double, used by ce_load only)")


if __name__ == "__main__":
    main()
