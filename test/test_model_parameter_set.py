"""Parameter-set YAML files: the three shipped reference sets and the exact round trip."""

from __future__ import annotations

import dataclasses

import pytest

from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.errors import ParameterFileError, ParameterValueError
from piezo_stage.model.parameter_set import (
    SHIPPED,
    Dynamics,
    ParameterSet,
    load_parameter_set,
    parameter_set_from_dict,
    parameter_set_to_dict,
    save_parameter_set,
    shipped_parameter_set,
)

pytestmark = pytest.mark.unit


def test_shipped_sets_hold_the_thesis_values():
    ch9 = shipped_parameter_set("ch9_example")
    assert ch9.form == "static" and ch9.dynamics is None
    assert ch9.bouc_wen == BoucWenParameters(kappa=(2.0,), kappa_w=2.0, rho=1.0, sigma=3.0, n=1.5)
    ch10 = shipped_parameter_set("ch10_patch")
    assert ch10.bouc_wen.kappa == (1.401e-7, -5.0949e-11) and ch10.bouc_wen.input_sign == -1
    assert (
        ch10.bouc_wen.kappa_w,
        ch10.bouc_wen.rho,
        ch10.bouc_wen.sigma,
        ch10.bouc_wen.n,
        ch10.bouc_wen.y0,
    ) == (9.22e-6, 0.0047, 0.812, 1.12, 1.7858e-6)
    ch11 = shipped_parameter_set("ch11_rig")
    assert ch11.form == "dynamic" and ch11.dynamics == Dynamics(m=5.3e-3, c=13.0)
    assert (ch11.bouc_wen.kappa_x, ch11.bouc_wen.kappa_w, ch11.bouc_wen.rho) == (
        10.35e6,
        43.57,
        8.566e4,
    )
    assert (ch11.bouc_wen.sigma, ch11.bouc_wen.n) == (0.9153, 1.176)
    assert (ch11.input_name, ch11.output_name) == ("voltage", "displacement")
    for name in SHIPPED:
        shipped_parameter_set(name).validate()


@pytest.mark.parametrize("name", SHIPPED)
def test_round_trip(name, tmp_path):
    ps = shipped_parameter_set(name)
    path = tmp_path / f"{name}.yaml"
    save_parameter_set(ps, path)
    assert load_parameter_set(path) == ps
    assert parameter_set_from_dict(parameter_set_to_dict(ps)) == ps


def test_round_trip_keeps_full_precision(tmp_path):
    ps = dataclasses.replace(
        shipped_parameter_set("ch10_patch"),
        bouc_wen=BoucWenParameters(
            kappa=(0.1 + 0.2, 1 / 3), kappa_w=2 / 7, rho=1e-300, sigma=0.5, n=1.0
        ),
        w0=-0.123456789012345678,
        notes="identified: rms 1e-9",
    )
    save_parameter_set(ps, tmp_path / "p.yaml")
    assert load_parameter_set(tmp_path / "p.yaml") == ps


def test_layout_errors(tmp_path):
    good = parameter_set_to_dict(shipped_parameter_set("ch11_rig"))
    with pytest.raises(ParameterFileError, match="unknown key"):
        parameter_set_from_dict(good | {"extra": 1})
    with pytest.raises(ParameterFileError, match="missing key"):
        parameter_set_from_dict({k: v for k, v in good.items() if k != "bouc_wen"})
    bad_bw = dict(good["bouc_wen"])
    del bad_bw["rho"]
    with pytest.raises(ParameterFileError, match="rho"):
        parameter_set_from_dict(good | {"bouc_wen": bad_bw})
    with pytest.raises(ParameterFileError, match="dynamics.m"):
        parameter_set_from_dict(good | {"dynamics": {"m": 0.0, "c": 1.0}})
    with pytest.raises(ParameterFileError, match="needs dynamics"):
        parameter_set_from_dict(good | {"dynamics": None})
    (tmp_path / "bad.yaml").write_text("name: [unclosed")
    with pytest.raises(ParameterFileError, match="not valid YAML"):
        load_parameter_set(tmp_path / "bad.yaml")
    with pytest.raises(ParameterFileError, match="cannot read"):
        load_parameter_set(tmp_path / "missing.yaml")
    with pytest.raises(ParameterFileError, match="unknown shipped"):
        shipped_parameter_set("nope")


def test_construction_errors():
    bw = BoucWenParameters(kappa=(1.0,), kappa_w=1.0, rho=1.0, sigma=1.0, n=1.0)
    with pytest.raises(ParameterValueError, match="form"):
        ParameterSet(name="x", form="quasi", bouc_wen=bw, dynamics=None)
    with pytest.raises(ParameterValueError, match="no dynamics"):
        ParameterSet(name="x", form="static", bouc_wen=bw, dynamics=Dynamics(1.0, 1.0))
    with pytest.raises(ParameterValueError, match="dynamics.c"):
        Dynamics(1.0, -1.0)
