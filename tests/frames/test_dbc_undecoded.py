"""Signals multiplexed by no multiplexer signal decode as cantools decodes them: not at all.

opendbc's vw_pq.dbc marks Motor_2's multiplexer ``m`` instead of ``M``, and its
``SG_MUL_VAL_`` lines give four signals multiplexer ids of it (issue 33, point 10): cantools
then leaves those signals out of the message's signal tree and never decodes or encodes them,
while canical's generated codec decoded them as plain overlapping signals, so the same frame
decoded differently (1 message of 4,483 in 72 real DBCs).
"""

from __future__ import annotations

import random
from pathlib import Path

import cantools
import pytest
import yaml

from canical.bus.daemon_config import load_config
from canical.errors import CanicalError
from canical.frames.codec import load_dbc
from canical.frames.compiler import codec_for
from canical.frames.dbc_files import DbcSet

#: Motor_2 as vw_pq.dbc defines it, multiplexer ``m`` and all.
MOTOR_2 = '''VERSION ""

NS_ :

BS_:

BU_: Motor Gateway

BO_ 648 Motor_2: 8 Motor
 SG_ MO2_Mp_Code m : 6|2@1+ (1,0) [0|3] "" Gateway
 SG_ MO2_Getr_Code m2 : 0|6@1+ (1,0) [0|63] "" Gateway
 SG_ MO2_max_Mo m3 : 0|6@1+ (10,0) [0|630] "Nm" Gateway
 SG_ MO2_CAN_Vers m0 : 0|6@1+ (1,0) [0|63] "" Gateway
 SG_ MO2_Motor_Code m1 : 0|6@1+ (1,0) [0|63] "" Gateway
 SG_ MO2_Kuehlm_T : 8|8@1+ (0.75,-48) [-47.25|142.5] "degC" Gateway
 SG_ MO2_BLS : 16|1@1+ (1,0) [0|1] "" Gateway
 SG_ MO2_Sta_GRA : 22|2@1+ (1,0) [0|3] "" Gateway
 SG_ MO2_RME_Gehalt : 29|3@1+ (12.5,0) [0|75] "%" Gateway
 SG_ MO2_GRA_Soll : 32|8@1+ (1.28,0) [0|325.12] "km/h" Gateway
 SG_ MO2_LL_Solldz : 40|8@1+ (10,0) [0|2540] "1/min" Gateway
 SG_ MO2_Begr_Mo : 48|8@1+ (0.39,0) [0|99.06] "%" Gateway
 SG_ MO2_Mo_ZWR : 56|8@1+ (0.39,0) [0|99.06] "%" Gateway

SG_MUL_VAL_ 648 MO2_Getr_Code MO2_Mp_Code 2-2;
SG_MUL_VAL_ 648 MO2_max_Mo MO2_Mp_Code 3-3;
SG_MUL_VAL_ 648 MO2_CAN_Vers MO2_Mp_Code 0-0;
SG_MUL_VAL_ 648 MO2_Motor_Code MO2_Mp_Code 1-1;
'''


@pytest.fixture
def dbc(tmp_path: Path) -> Path:
    path = tmp_path / "vw_motor_2.dbc"
    path.write_text(MOTOR_2)
    return path


@pytest.mark.parametrize("compiled", [True, False])
def test_motor_2_decodes_and_encodes_as_cantools(dbc: Path, compiled: bool) -> None:
    reference = cantools.database.load_file(str(dbc), strict=False).get_message_by_name("Motor_2")
    message = load_dbc(DbcSet((dbc,))).get_message_by_name("Motor_2")
    codec = codec_for(message, compiled=compiled)
    assert "MO2_Getr_Code" not in codec.names and "MO2_Kuehlm_T" in codec.names
    rng = random.Random(7)
    for _ in range(300):
        payload = bytes(rng.getrandbits(8) for _ in range(8))
        want = reference.decode(payload, decode_choices=False)
        got = dict(zip(codec.names, codec.decode(payload), strict=True))
        assert got == want, payload.hex()
        assert codec.encode(list(got.values())) == reference.encode(want, strict=False)


def test_naming_a_signal_cantools_never_decodes_is_one_line(dbc: Path, tmp_path: Path) -> None:
    content = {"bus": {"interface": "virtual", "channel": "x"}, "dbc": str(dbc),
               "axes": {"z": {"coefficients": str(tmp_path / "z.yaml")}},
               "inputs": {"gear": {"signal": "Motor_2.MO2_Getr_Code"}}}
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(content))
    with pytest.raises(CanicalError, match=r"inputs.gear.signal: signal MO2_Getr_Code of Motor_2 is "
                                           r"multiplexed, but no signal of Motor_2 is its multiplexer"):
        load_config(path)
    content["inputs"] = {"coolant_c": {"signal": "Motor_2.MO2_Kuehlm_T"}}
    path.write_text(yaml.safe_dump(content))
    assert load_config(path).inputs["coolant_c"].message == "Motor_2"
