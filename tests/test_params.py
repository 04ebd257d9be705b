"""Every parameter is type-checked and range-checked; an override is applied whole or not at all."""

from __future__ import annotations

import dataclasses
import typing

import msgspec
import pytest

from onboard.contracts import params as P
from robot_description import params as rd
from services.runtime.config import ConfigError, load_params


def test_an_int_field_refuses_a_float_and_a_bool():
    with pytest.raises(ValueError, match=r"planner\.nodes: expected `int`, got `float`"):
        P.with_overrides(P.PlannerParams(), {"nodes": 1.5})
    with pytest.raises(ValueError, match=r"planner\.nodes: expected `int`, got `bool`"):
        P.with_overrides(P.PlannerParams(), {"nodes": True})
    assert P.with_overrides(P.PlannerParams(), {"nodes": 1200}).nodes == 1200


def test_a_tuple_of_ints_refuses_none_and_strings():
    hw = P.HardwareParams()
    with pytest.raises(ValueError, match=r"hardware\.node_ids\[1\]: expected `int`, got `null`"):
        P.with_overrides(hw, {"node_ids": (1, None, 3, 4)})
    with pytest.raises(ValueError, match=r"hardware\.node_ids: expected `array`, got `null`"):
        P.with_overrides(hw, {"node_ids": None})
    with pytest.raises(ValueError, match=r"hardware\.node_ids: expected `array`, got `str`"):
        P.with_overrides(hw, {"node_ids": "1234"})
    with pytest.raises(ValueError, match=r"hardware\.node_ids\[0\]: expected `int` <= 127"):
        P.with_overrides(hw, {"node_ids": (128, 2, 3, 4)})  # not a CANopen node id
    assert P.with_overrides(hw, {"node_ids": [4, 3, 2, 1]}).node_ids == (4, 3, 2, 1)  # a TOML array becomes the tuple


def test_a_float_field_takes_an_int_and_stores_a_float():
    s = P.with_overrides(P.SafetyLimits(), {"wheel_torque_max": 1})
    assert s.wheel_torque_max == 1.0 and type(s.wheel_torque_max) is float


def test_out_of_range_values_are_refused_naming_the_field():
    with pytest.raises(ValueError, match=r"safety\.wheel_torque_max: expected `float` <= 15\.0 \(value 1000\)"):
        P.with_overrides(P.SafetyLimits(), {"wheel_torque_max": 1000})
    with pytest.raises(ValueError, match=r"control\.kp_tilt: expected `float` >= 0\.0"):
        P.with_overrides(P.ControlParams(), {"kp_tilt": -1.0})
    with pytest.raises(ValueError, match=r"control\.kp_tilt"):
        P.with_overrides(P.ControlParams(), {"kp_tilt": float("nan")})
    with pytest.raises(ValueError, match=r"control\.rate_hz: expected `float` >= 100\.0"):
        P.with_overrides(P.ControlParams(), {"rate_hz": 0.0})
    with pytest.raises(ValueError, match=r"control\.policy: invalid enum value 'pid'"):
        P.with_overrides(P.ControlParams(), {"policy": "pid"})
    with pytest.raises(ValueError, match=r"control\.auto_arm: expected `bool`, got `int`"):
        P.with_overrides(P.ControlParams(), {"auto_arm": 1})
    with pytest.raises(ValueError, match=r"control\.kp_tilt"):
        P.ControlParams(kp_tilt=-1.0)  # a section cannot be built out of range either


def test_an_override_is_all_or_nothing_and_names_every_bad_field():
    before = P.ControlParams()
    with pytest.raises(ValueError) as err:
        P.with_overrides(before, {"kp_tilt": 41.0, "kd_tilt": -3.0, "tube_window": 2.5})
    assert "control.kd_tilt" in str(err.value) and "control.tube_window" in str(err.value)
    assert "control.kp_tilt" not in str(err.value)
    assert before.kp_tilt == 40.0
    with pytest.raises(ValueError, match=r"control has no parameter 'kp_roll'"):
        P.with_overrides(before, {"kp_tilt": 41.0, "kp_roll": 1.0})


def test_relations_between_fields_are_checked():
    with pytest.raises(ValueError, match=r"hardware\.reconnect_min_s"):
        P.with_overrides(P.HardwareParams(), {"reconnect_min_s": 2.0})
    with pytest.raises(ValueError, match=r"perception\.clusters_min"):
        P.with_overrides(P.PerceptionParams(), {"clusters_min": 30})


def _bounds(hint: typing.Any) -> tuple[typing.Any, list[msgspec.Meta]]:
    if typing.get_origin(hint) is typing.Annotated:
        base, *extra = typing.get_args(hint)
        return base, [m for m in extra if isinstance(m, msgspec.Meta)]
    return hint, []


@pytest.mark.parametrize("section", sorted(P.SECTIONS))
def test_every_number_has_a_range_and_every_field_a_type(section: str):
    cls = P.SECTIONS[section]
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        base, metas = _bounds(hints[f.name])
        if typing.get_origin(base) is tuple:
            base, metas = _bounds(typing.get_args(base)[0])
        if base in (int, float):
            low = any(m.ge is not None or m.gt is not None for m in metas)
            high = any(m.le is not None or m.lt is not None for m in metas)
            assert low and high, f"{section}.{f.name} has no range"
        else:
            assert base in (bool, str) or typing.get_origin(base) is typing.Literal, f"{section}.{f.name}: {base}"


def test_ceilings_are_those_of_the_robot_description():
    robots = [rd.robot_params(v) for v in rd.VARIANTS]
    assert P.WHEEL_TORQUE_PEAK == max(r.wheel_torque_peak for r in robots)
    assert P.FOOT_TORQUE_PEAK == max(r.foot_torque_peak for r in robots)
    assert P.WHEEL_NO_LOAD_SPEED == max(r.wheel_no_load_speed for r in robots)


def test_restart_fields_exist_and_changes_are_named():
    for section, names in P.NEEDS_RESTART.items():
        assert names <= {f.name for f in dataclasses.fields(P.SECTIONS[section])}
    before = P.ControlParams()
    after = P.with_overrides(before, {"rate_hz": 500.0, "kp_tilt": 41.0, "hop_height": 0.1})
    assert P.restart_changes("control", before, after) == ["control.hop_height", "control.rate_hz"]
    assert P.restart_changes("safety", P.SafetyLimits(), P.SafetyLimits(wheel_torque_max=1.0)) == []


def test_a_config_file_with_a_bad_value_names_file_and_field(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[planner]\nnodes = 1.5\n")
    with pytest.raises(ConfigError, match=r"bad\.toml: \[planner\] planner\.nodes: expected `int`"):
        load_params(path)
    path.write_text("[safety]\nwheel_torque_max = 1.2\n[hardware]\nnode_ids = [1, 2, 3, 4]\n")
    params = load_params(path)
    assert params["safety"].wheel_torque_max == 1.2 and params["hardware"].node_ids == (1, 2, 3, 4)


def test_an_identified_robot_is_named_once_for_the_estimator_and_the_low_level(tmp_path):
    """The estimator places the CoM by archer identify's offset and the balance observer starts from
    it without counting it again: a file that gives it to one of them only, or two different files, is refused."""
    def config(text: str):
        path = tmp_path / "robot.toml"
        path.write_text(text)
        return load_params(path)

    both = config('[estimator]\nidentified = "id.toml"\n[control]\nidentified = "id.toml"\n')
    assert both["estimator"].identified == both["control"].identified == "id.toml"
    assert config('[estimator]\nrobot = "indoor"\n[control]\nkp_tilt = 40.0\n')["control"].identified == ""
    for text in ('[estimator]\nidentified = "id.toml"\n',
                 '[estimator]\nidentified = "id.toml"\n[control]\nkp_tilt = 40.0\n',
                 '[estimator]\nidentified = "a.toml"\n[control]\nidentified = "b.toml"\n'):
        with pytest.raises(ConfigError, match=r"robot\.toml: archer identify's file goes in both"):
            config(text)
