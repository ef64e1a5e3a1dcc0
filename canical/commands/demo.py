"""``canical demo``: the whole product on one machine, with no hardware.

1. The paper: a simulated turntable session on the paper's protocol,
   calibrated with every model, judged on a second session at rates between
   the training ones and on the paper's ±25 deg/s validation records.
2. The closed loop: a session from a sensor with an effect nobody declared
   (a temperature-dependent bias and scale factor, recorded beside channels
   that carry only noise); the loop finds it, adds it, and reports the error
   before and after on held-out plateaus, with plots.

Everything it writes goes to one folder.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from canical.atomic_file import make_dirs, write_text_atomic
from canical.commands import COMMANDS
from canical.output_plan import output_plan

# The simulator and the fitting modules (numpy, scipy, matplotlib) are imported where they are
# used, so that `--help` and argument errors answer at once.


def register(sub) -> None:
    p = sub.add_parser("demo", help=COMMANDS["demo"])
    p.add_argument("--out", default="canical-demo", help="folder for the files it writes [canical-demo]")
    p.add_argument("--seed", type=int, default=0, help="simulation seed [0]")
    p.add_argument("--no-bus", action="store_true",
                   help="skip the CAN part (emulated IMU, recording, download, live correction)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    with output_plan(dirs=[args.out]):
        return demo(args)


def demo(args: argparse.Namespace) -> int:
    """All parts; the files appear in ``--out`` together when the demo has succeeded."""
    import numpy as np

    from canical.commands.calibrate import report_json
    from canical.evaluation import compare_models, held_out_set_errors, validation_record
    from canical.pipeline import CalibrateOptions, calibrate
    from canical.sessions.csv_file import format_session
    from canical.sets import coefficient_file
    from canical.sim.sessions import between_rates_session, constant_session, paper_session

    out = Path(args.out)
    make_dirs(out)
    train = paper_session(seed=args.seed)
    test = between_rates_session(seed=args.seed + 1)
    write_text_atomic(out / "session.csv", format_session(train))
    print(f"simulated a turntable session: -60..60 deg/s in 3 deg/s steps, {len(train)} samples")
    print(f"  -> {out / 'session.csv'}\n")

    scores = compare_models(train, test)
    print("error on held-out plateaus: plateau means of a second session, at rates between the "
          "training rates, deg/s:")
    print(f"  {'model':46s} {'train rms':>10s} {'held-out rms':>13s} {'held-out max':>13s}")
    for s in scores:
        print(f"  {s.label:46s} {s.train_rms_dps:10.4f} {s.test_rms_dps:13.4f} {s.test_max_dps:13.4f}")
    common = next(s for s in scores if s.label.startswith("segmented-linear"))
    paper = next(s for s in scores if "4 seg" in s.label)
    ours = scores[-1]
    print(f"\n  improved (paper) vs common model: {common.test_rms_dps / paper.test_rms_dps:.1f}x lower rms")
    print(f"  improved (ours)  vs common model: {common.test_rms_dps / ours.test_rms_dps:.1f}x lower rms")

    print("\nvalidation records, 50,000 samples each, sliding mean of 100 (the paper's Fig. 3):")
    for rate in (25.0, -25.0):
        record = constant_session(None, rate, seed=args.seed + 7)
        parts = []
        for s in (common, paper, ours):
            v = validation_record(s.model, s.v0, record)
            parts.append(
                f"{s.label.split(' (')[0].split(',')[0]}{' (ours)' if s is ours else ''} "
                f"{v.mean_error_dps:+.4f}"
            )
        print(f"  {rate:+.0f} deg/s: mean error  " + " | ".join(parts))

    result = calibrate(train, CalibrateOptions(), sensor_id="SIM-0001", axis="z")
    coefficient_file.save(out / "coefficients.yaml", result.coefficients)
    write_text_atomic(out / "report.json", report_json(result.report))
    written = held_out_set_errors(result.coefficients, test)
    print(f"\nwrote {out / 'coefficients.yaml'} ({result.report.written_model()}) and {out / 'report.json'}")
    print(f"  the written set on the second session: held-out rms {np.sqrt(np.mean(written**2)):.4f}, max "
          f"{np.max(np.abs(written)):.4f} deg/s (the table's scheme); `canical calibrate` on session.csv "
          f"alone reports {result.report.held_out.rms_dps:.4f} (whole table rates left out)")
    closed_loop_demo(out, args.seed)

    # --- The IMU on a CAN bus (canical/commands/demo_bus.py): emulated device, session recorded from the
    # bus, calibration, download over CANopen SDO, live on-device correction checked against apply.
    if not args.no_bus:
        from canical.commands.demo_bus import BusDemoOptions, default_bus, run_bus_demo

        interface, channel = default_bus()
        print(f"\n--- the IMU on a CAN bus ({interface} {channel}) ---")
        run_bus_demo(out / "bus", replace(BusDemoOptions(), interface=interface, channel=channel))
    return 0


def closed_loop_demo(out: Path, seed: int) -> Path:
    """Part 2: an undeclared effect, found and corrected; returns the coefficient file written."""
    from canical.commands.calibrate import write_report_dir
    from canical.pipeline import CalibrateOptions, calibrate
    from canical.sessions.csv_file import format_session
    from canical.sets import coefficient_file
    from canical.sim.scenarios import SCENARIOS

    scenario = next(s for s in SCENARIOS if s.name.startswith("temperature bias + scale"))
    session = scenario.session(seed)
    path = out / "session_with_effect.csv"
    write_text_atomic(path, format_session(session))
    channels = ", ".join(session.aux)
    print(f"\n--- closing the loop ---\nsimulated a sensor with an undeclared effect; recorded channels: "
          f"{channels}\n  -> {path}")
    result = calibrate(session, CalibrateOptions(), sensor_id="SIM-0001", axis="z")
    loop = result.loop
    assert loop is not None, "the default options close the loop"
    print("held-out rms, deg/s (2 s blocks, whole plateaus left out), step by step:")
    for e in result.report.effects:
        terms = ", ".join(f"{t['feature']}/{t['form']}" for t in e.terms)
        ev = e.evidence
        print(f"  (found {e.name} ({terms}): held-out gain {ev.held_out_gain:.0%} when added, "
              f"p = {ev.p_value:.1e})")
    for step in loop.steps:
        print(f"  {step.held_out_rms_dps:.4f}  {step.step} ({step.spec})")
    print(f"written set: held-out rms {loop.rms_after:.4f} deg/s, "
          f"{loop.rms_before / loop.rms_after:.0f}x lower than the rate model alone")
    coeffs = out / "coefficients_with_effect.yaml"
    coefficient_file.save(coeffs, result.coefficients)
    write_report_dir(out / "report", result.report.with_paths(str(path), str(coeffs)), loop)
    print(f"wrote {coeffs} and {out / 'report'}/ (report.md, plots)")
    return coeffs
