"""``canical demo``: the whole product on one machine, with no hardware.

1. The paper: a simulated turntable session on the paper's protocol,
   calibrated with every model, judged on a second session at rates between
   the training ones and on the paper's ±25 deg/s validation records.
2. The closed loop: a session from a sensor with an effect nobody declared
   (a temperature-dependent bias and scale factor, recorded beside channels
   that carry only noise); the loop finds it, adds it, and reports the error
   before and after on held-out plateaus, with plots.
3. The IMU as three axes: a simulated triad with cross-axis coupling, one
   session per table axis and one turning about all three at once; one IMU
   set calibrated, judged on the multi-axis plateaus per axis and coupled.

Everything it writes goes to one folder.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from canical.commands import COMMANDS
from canical.files.atomic_file import make_dirs, write_text_atomic
from canical.files.output_plan import output_plan

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

    from canical.calibration.evaluation import compare_models, held_out_set_errors, validation_record
    from canical.calibration.pipeline import CalibrateOptions, calibrate
    from canical.commands.calibrate import report_json
    from canical.models.kinds import SEGMENTED_LINEAR
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
    common = next(s for s in scores if s.label.startswith(SEGMENTED_LINEAR.name))
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

    triad_demo(out / "triad", args.seed)
    # --- The IMU on a CAN bus (canical/commands/demo_bus.py): emulated device, session recorded from the
    # bus, calibration, download over CANopen SDO, live on-device correction checked against apply.
    if not args.no_bus:
        from canical.commands.demo_bus import BusDemoOptions, default_bus, run_bus_demo

        interface, channel = default_bus()
        print(f"\n--- the IMU on a CAN bus ({interface} {channel}) ---")
        run_bus_demo(out / "bus", replace(BusDemoOptions(), interface=interface, channel=channel))
    return 0


def triad_demo(out: Path, seed: int) -> Path:
    """Part 3: a triad's coupling calibrated with its per-axis models; returns the IMU set written."""
    import json

    import numpy as np

    from canical.calibration.imu_pipeline import calibrate_imu
    from canical.calibration.pipeline import CalibrateOptions
    from canical.commands.calibrate_imu import write_report_dir
    from canical.sessions.triad_session import format_triad_session
    from canical.sets import imu_set
    from canical.sim.triad import axis_session, multi_axis_rates, multi_axis_session, random_triad

    make_dirs(out)
    triad = random_triad(seed)
    sessions = [axis_session(triad, axis, dwell_s=2.0, seed=100 * seed + k, sensor="SIM-TRIAD")
                for k, axis in enumerate(("x", "-y", "z"))]
    sessions.append(multi_axis_session(triad, multi_axis_rates(12, seed=seed), dwell_s=3.0,
                                       seed=100 * seed + 9, sensor="SIM-TRIAD"))
    names = ["x.csv", "neg_y.csv", "z.csv", "multi.csv"]
    for name, session in zip(names, sessions, strict=True):
        write_text_atomic(out / name, format_triad_session(session))
    off = np.abs(triad.coupling - np.diag(np.diag(triad.coupling))).max()
    print(f"\n--- the IMU as three axes ---\nsimulated a triad (cross-axis coupling up to {off:.1%}): one "
          f"session per table axis (x, -y, z) and one turning about all three at once")
    result = calibrate_imu(sessions, CalibrateOptions(), sensor_id="SIM-TRIAD")
    path = out / "imu.yaml"
    imu_set.save(path, result.imu_set)
    report = result.report([str(out / n) for n in names], str(path))
    write_text_atomic(out / "report.json", json.dumps(report.to_dict(), indent=2) + "\n")
    write_report_dir(out / "report", report)
    check = result.errors[-1]
    before = float(np.sqrt(np.mean(np.square(check.before_rms_dps))))
    after = float(np.sqrt(np.mean(np.square(check.after_rms_dps))))
    print(f"multi-axis plateaus ({check.plateaus}), error rms over x, y, z: each axis's set alone "
          f"{before:.4f} deg/s, with the coupling {after:.4f} deg/s ({before / after:.0f}x lower)")
    print(f"wrote {path} (the IMU set) and {out / 'report'}/ (report.md, coupling.png)")
    return path


def closed_loop_demo(out: Path, seed: int) -> Path:
    """Part 2: an undeclared effect, found and corrected; returns the coefficient file written."""
    from canical.calibration.pipeline import CalibrateOptions, calibrate
    from canical.commands.calibrate import write_report_dir
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
    print(f"held-out rms, deg/s ({loop.blocks.label}, whole plateaus left out), step by step:")
    for e in result.report.effects:
        terms = ", ".join(f"{t.feature}/{t.form}" for t in e.terms)
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
