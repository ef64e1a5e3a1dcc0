"""Why a sweep loses to a step session: per seed of ``bench_sweep.py``, what each suspect does.

Prints figures; asserts nothing. Run: python tests/benchmarks/why_sweep.py --seeds S,S,...

The same sensor, step session, sweep and third session as ``bench_sweep.py`` at each seed; every
error here is judged on the third session **without its noise** (the sensor's response at the
rates midway, exactly), so the figures show the calibrations, not the judge's noise. Columns:

* ``step``, ``sweep``: each session calibrated as ``canical calibrate`` does; their sizes;
* ``step'``: the step session recorded again with other noise (is the comparator lucky?);
* ``sweep'``: the sweep recorded again with other noise (is the sweep unlucky?);
* ``exact``: the sweep with an exact, prompt reference (do the encoder's steps and latency matter?);
* ``no loop``: the sweep without the closed loop (does the loop add something?);
* ``@step pts``: the sweep's windows fitted at the step session's segment points and size, which
  says whether the windows can fit as well as the plateaus given where to join the segments.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads its BLAS

import argparse
from dataclasses import dataclass, replace

import numpy as np
from bench_sweep import draw_programme, draw_sensor

from canical.calibrate.model_fit import dv_span
from canical.calibrate.plateaus import detect_plateaus, plateau_means
from canical.calibration.evaluation import held_out_set_errors
from canical.calibration.pipeline import CalibrateOptions, calibrate, fit_base
from canical.models import RateModel
from canical.models.segmented_inverse import fit_segmented_inverse
from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import between_rates_session, paper_session
from canical.sim.sweeps import SweepProgramme, sweep_recording


@dataclass(frozen=True)
class Recorded:
    """One seed's sensor, its sessions' noise seeds and the sweep's programme, as bench_sweep draws them."""

    gyro: GyroModel
    programme: SweepProgramme
    step_seed: int
    sweep_seed: int
    judge: Session  # the third session, noise-free


def recorded(seed: int) -> Recorded:
    rng = np.random.default_rng(seed)
    gyro = draw_sensor(rng)
    seeds = [int(s) for s in rng.integers(0, 2**31, size=3)]
    step = paper_session(gyro, seed=seeds[0])
    programme = draw_programme(rng, float(step.time_s[-1] - step.time_s[0]))
    judge = between_rates_session(replace(gyro, noise_dps=0.0, lsb=0.0), seed=seeds[2])
    return Recorded(gyro, programme, seeds[0], seeds[1], judge)


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x**2)))


def calibrated(session: Session, judge: Session,
               options: CalibrateOptions | None = None) -> tuple[float, str]:
    """(error on the noise-free third session, deg/s rms; the written model's size)."""
    result = calibrate(session, options or CalibrateOptions(), sensor_id="SIM", axis="z")
    loop = result.report.closed_loop
    spec = loop.final_spec if loop is not None else result.report.spec
    size = spec.split("segments=")[1].replace(" joins=C0", "")
    return rms(held_out_set_errors(result.coefficients, judge)), size


def at_step_points(step: Session, sweep: Session, spec: str, judge: Session) -> float:
    """The sweep's windows fitted at the segment points the step session chose for ``spec``."""
    segments, order = (int(part.split("=")[-1]) for part in spec.split()[:2])
    sized = CalibrateOptions(segments=segments, order=order, extend=False)
    knots = fit_base(step, sized).fitted.model.knots
    base = fit_base(sweep, sized)
    span = dv_span(base.points)
    fit = fit_segmented_inverse(base.points.dv, base.points.rate, base.points.weight, knots, order,
                                scale=max(abs(span[0]), abs(span[1])), span=span, smoothness=0)
    model: RateModel = fit.poly
    return judged_model(model, base.v0, judge)


def judged_model(model: RateModel, v0: float, judge: Session) -> float:
    """A model's error on the third session's plateau means, with the V0 it was fitted with."""
    plateaus = detect_plateaus(judge.time_s, judge.reference())
    return rms(model.evaluate(plateau_means(judge.raw, plateaus) - v0)[0] - plateaus.rate_dps)


def one_seed(seed: int) -> str:
    r = recorded(seed)
    step = paper_session(r.gyro, seed=r.step_seed)
    sweep = sweep_recording(r.gyro, r.programme, seed=r.sweep_seed)
    step_err, step_spec = calibrated(step, r.judge)
    sweep_err, sweep_spec = calibrated(sweep, r.judge)
    step_again = calibrated(paper_session(r.gyro, seed=r.step_seed + 1), r.judge)[0]
    sweep_again = calibrated(sweep_recording(r.gyro, r.programme, seed=r.sweep_seed + 1), r.judge)[0]
    exact = replace(r.programme, encoder_lsb_dps=1e-6, ref_latency_s=0.0)
    exact_err = calibrated(sweep_recording(r.gyro, exact, seed=r.sweep_seed), r.judge)[0]
    no_loop = calibrated(sweep, r.judge, CalibrateOptions(extend=False))[0]
    at_step = at_step_points(step, sweep, step_spec, r.judge)
    g = r.gyro
    return (f"{seed:6d} {g.noise_dps:5.3f} {g.asymmetry_width_dps:4.1f} {60 * g.ripple:5.3f} "
            f"{r.programme.encoder_lsb_dps:5.3f} | {step_err:.5f} {step_again:.5f} | {sweep_err:.5f} "
            f"{sweep_again:.5f} {exact_err:.5f} {no_loop:.5f} {at_step:.5f} | {sweep_err / step_err:5.2f} "
            f"{at_step / step_err:5.2f} | {step_spec:18s} {sweep_spec}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="70000,70001", help="bench_sweep seeds (comma-separated)")
    args = parser.parse_args()
    print("errors on the third session without its noise, deg/s rms; sizes: segments, order")
    print("  seed noise knee ripple  lsb  |  step    step'   |  sweep   sweep'   exact  no loop "
          "@step pts | sweep/step @pts/step | step size / sweep size")
    for seed in (int(s) for s in args.seeds.split(",")):
        print(one_seed(seed), flush=True)


if __name__ == "__main__":
    main()
