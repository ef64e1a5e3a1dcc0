"""``canical emulate``: run an emulated canical IMU node on a CAN interface.

The node streams raw TPDOs from the simulator, answers SDO on the IMU's object
dictionary, keeps its coefficient banks in a state file (so a restart keeps what
was stored) and can correct its own samples (``--correct``). Prints one
``ready`` line when it answers SDO, so scripts and tests can wait for it;
stops on SIGTERM/SIGINT or after ``--duration``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from pathlib import Path
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.commands.stop_signals import event_on_signals
from canical.device.can_network import (
    add_bus_arguments,
    bus_options,
    disconnect_quietly,
    open_network,
    reconnect_network,
    sdo_server_filters,
)
from canical.errors import CanicalError
from canical.files.output_plan import check_dir, check_file
from canical.frames.imu_dictionary import AXES

if TYPE_CHECKING:
    from canical.sim.gyro import Effect


def _rates(text: str) -> tuple[float, ...]:
    """``-60:60:3`` (from:to:step) or a comma list of rates."""
    try:
        if ":" in text:
            lo, hi, step = (float(x) for x in text.split(":"))
            n = round((hi - lo) / step)
            return tuple(lo + step * i for i in range(n + 1))
        return tuple(float(x) for x in text.split(","))
    except (ValueError, ZeroDivisionError):
        raise argparse.ArgumentTypeError(f"{text!r}: give FROM:TO:STEP or a comma list of deg/s") from None


def register(sub) -> None:
    p = sub.add_parser("emulate", help=COMMANDS["emulate"])
    add_bus_arguments(p)
    p.add_argument("--node", type=lambda s: int(s, 0), default=0x10, help="CANopen node id [0x10]")
    p.add_argument("--serial", type=int, default=4711, help="serial number (0x1018 sub 4) [4711]")
    p.add_argument("--state", help="state file of the banks [~/.local/state/canical/imu-SERIAL.json]")
    p.add_argument("--rated-range", type=float, default=50.0, help="rated range, deg/s, all axes [50]")
    p.add_argument("--rate", type=float, default=100.0,
                   help="samples per simulated second [100]; 0: SDO only")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second [1]")
    p.add_argument("--table", choices=("steps", "constant", "still"), default="steps",
                   help="rate table motion [steps]")
    p.add_argument("--table-axis", choices=AXES, default="z", help="axis the table turns [z]")
    p.add_argument("--table-rates", type=_rates, default=_rates("-60:60:3"),
                   help="plateau rates for --table steps, FROM:TO:STEP or list [-60:60:3]")
    p.add_argument("--dwell", type=float, default=3.0, help="seconds per plateau [3]")
    p.add_argument("--table-rate", type=float, default=25.0, help="rate for --table constant [25]")
    p.add_argument("--no-table-ref", action="store_true", help="do not send TABLE_REF (not on a table)")
    t = p.add_argument_group("table recording (--table steps): move and report as a real table does")
    t.add_argument("--table-accel", type=float, metavar="DPS2",
                   help="acceleration limit of rate changes, deg/s² (down to 1) [100, no other effect]")
    t.add_argument("--table-jerk", type=float, metavar="DPS3", help="jerk limit: S-curve rate changes")
    t.add_argument("--table-overshoot", type=float, default=0.0, metavar="FRACTION",
                   help="servo overshoot with damped ringing, fraction of each step, e.g. 0.1 [0]")
    t.add_argument("--table-measured", type=float, metavar="DPS",
                   help="TABLE_REF is the measured rate with this jitter, deg/s rms (else the commanded)")
    t.add_argument("--table-ref-rate", type=float, metavar="HZ",
                   help="TABLE_REF frames at this rate on the table's own clock (else one per sample)")
    t.add_argument("--table-latency", type=float, default=0.0, metavar="S",
                   help="TABLE_REF late by this much, s [0]")
    t.add_argument("--lost-rows", type=float, default=0.0, metavar="FRACTION",
                   help="fraction of the IMU's samples whose frames are lost, in bursts of ~0.1 s [0]")
    p.add_argument("--temp-bias", type=float, default=0.0,
                   help="undeclared effect: bias in deg/s per degC of die temperature above 25 [0]")
    p.add_argument("--temp-scale", type=float, default=0.0,
                   help="undeclared effect: scale-factor error per degC above 25, e.g. 2e-4 [0]")
    p.add_argument("--warmup", type=float, default=0.0, metavar="DPS",
                   help="undeclared effect: bias decaying after power-on, deg/s at t=0 [0]")
    p.add_argument("--warmup-tau", type=float, default=200.0, help="its time constant, s [200]")
    p.add_argument("--supply-bias", type=float, default=0.0,
                   help="undeclared effect: bias in deg/s per volt of supply above 5 V [0]")
    p.add_argument("--direction-offset", type=float, default=0.0,
                   help="undeclared effect: offset in deg/s, sign following the last rate change [0]")
    p.add_argument("--correct", action="store_true", help="on-device correction on from the start")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(run=run)


def undeclared_effects(args: argparse.Namespace) -> tuple:
    """The effects the options switch on, which the calibrator is not told about."""
    from canical.sim import effects as fx

    out: list[Effect] = []
    if args.temp_bias or args.temp_scale:
        out.append(fx.TemperatureEffect(channel="temp_c", reference_c=25.0,
                                        bias_dps_per_c=args.temp_bias, scale_per_c=args.temp_scale))
    if args.warmup:
        out.append(fx.WarmupEffect(amplitude_dps=args.warmup, tau_s=args.warmup_tau))
    if args.supply_bias:
        out.append(fx.SupplyEffect(channel="supply_v", reference_v=5.0, bias_dps_per_v=args.supply_bias))
    if args.direction_offset:
        out.append(fx.DirectionEffect(offset_dps=args.direction_offset))
    return tuple(out)


def table_recording(args: argparse.Namespace):
    """The table behaviour the options describe (None: the plain ramped steps)."""
    asked = (args.table_accel, args.table_jerk, args.table_measured, args.table_ref_rate)
    if all(v is None for v in asked) and not (args.table_overshoot or args.table_latency or args.lost_rows):
        return None
    from canical.sim.table_recording import TableBehaviour

    return TableBehaviour(
        accel_dps2=args.table_accel if args.table_accel is not None else 100.0,
        jerk_dps3=args.table_jerk,
        overshoot=args.table_overshoot,
        reference="measured" if args.table_measured is not None else "commanded",
        jitter_dps=args.table_measured or 0.0,
        encoder_lsb_dps=0.0001 if args.table_measured is not None else 0.0,
        ref_rate_hz=args.table_ref_rate,
        asynchronous=args.table_ref_rate is not None,
        ref_latency_s=args.table_latency,
        loss_fraction=args.lost_rows,
    )


def stream_config(args: argparse.Namespace):
    """The simulator settings the options describe (None for an SDO-only device)."""
    if args.rate <= 0:
        return None
    from canical.sim.imu_stream import StreamConfig, TableMotion, default_gyros

    gyros = default_gyros()
    effects = undeclared_effects(args)
    if effects:
        from dataclasses import replace

        gyros = {a: replace(g, effects=(*g.effects, *effects)) for a, g in gyros.items()}
    table = TableMotion(kind=args.table, axis=args.table_axis, rates_dps=args.table_rates,
                        dwell_s=args.dwell, rate_dps=args.table_rate, recording=table_recording(args))
    return StreamConfig(sample_rate_hz=args.rate, table=table, gyros=gyros, seed=args.seed)


def run(args: argparse.Namespace) -> int:
    from canical.device.emulated_imu import EmulatedImu, EmulatorConfig, ReceiveErrors, state_path_default

    if args.speed <= 0:
        raise CanicalError("--speed must be positive")
    logging.basicConfig(level=logging.INFO, format="emulate: %(message)s", stream=sys.stderr)
    for noisy in ("canopen", "can"):  # per-transfer chatter at INFO
        logging.getLogger(noisy).setLevel(logging.WARNING)
    # During a bus outage canopen logs every failed send; the device logs the outage itself.
    logging.getLogger("canopen.network").setLevel(logging.CRITICAL)
    config = EmulatorConfig(
        node_id=args.node,
        serial=args.serial,
        state_path=Path(args.state) if args.state else state_path_default(args.serial),
        rated_range_dps=dict.fromkeys(AXES, args.rated_range),
        stream=stream_config(args),
        speed=args.speed,
        table_ref=not args.no_table_ref,
        correction=args.correct,
    )
    assert config.state_path is not None  # set just above
    check_dir(config.state_path.parent)  # the device's flash: refused now, not at its first store
    config.state_path.parent.mkdir(parents=True, exist_ok=True)
    check_file(config.state_path)
    options = {"can_filters": sdo_server_filters(args.node), **bus_options(args)}
    network = open_network(args.interface, args.channel, listeners=[ReceiveErrors()], **options)
    try:
        def reopen() -> None:
            reconnect_network(network, args.interface, args.channel, **options)

        device = EmulatedImu(config, network, reopen=reopen, bus_name=f"{args.interface} {args.channel}")
        with event_on_signals(device.stop_event):
            if args.duration is not None:  # from now, whatever the bus does meanwhile (it may be down)
                stopper = threading.Timer(args.duration, device.stop_event.set)
                stopper.daemon = True
                stopper.start()
            device.boot_up()
            print(f"ready node 0x{args.node:02x} serial {args.serial} on {args.interface} {args.channel}",
                  flush=True)
            device.run()
    finally:
        disconnect_quietly(network)
    return 0
