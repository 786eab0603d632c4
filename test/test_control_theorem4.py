"""Theorem 4 (11.6-11.7) on the §11.4.1 bounds, bounds YAML loading, config lookup."""

import math

import pytest

from piezo_stage.config_path import ConfigNotFoundError, find_config
from piezo_stage.control.bounds import (
    THESIS_NOMINAL_PLANT,
    Bounds,
    load_bounds,
    load_nominal_plant,
    thesis_bounds_path,
)
from piezo_stage.control.errors import BoundsError, GainError
from piezo_stage.control.theorem4 import k0_max, k2_min, validate_gains

pytestmark = pytest.mark.unit

THESIS = Bounds(
    m_min=3.98e-3,
    m_max=6.63e-3,
    c_max=13.43,
    kappa_x_max=10.8e6,
    kappa_w_max=48.74,
    sigma_max=0.9212,
    rho_max=9.510e4,
)


def test_shipped_file_holds_the_thesis_bounds_and_nominal_plant():
    path = thesis_bounds_path()
    assert path == find_config("thesis_rig_bounds.yaml")
    assert load_bounds(path) == THESIS
    assert load_nominal_plant(path) == THESIS_NOMINAL_PLANT


def test_find_config_names_where_it_looked():
    with pytest.raises(ConfigNotFoundError, match="no_such_file.yaml"):
        find_config("no_such_file.yaml")


def test_k2_min_and_k0_max_as_printed_not_as_quoted():
    # (11.6)-(11.7) evaluated by hand with the §11.4.1 bounds (docs/design.md §7 erratum)
    expected_k2 = math.sqrt(2 * 6.63e-3 * (0.9212 * 9.510e4 * 48.74 + 10.8e6 + 5e6))
    assert k2_min(THESIS, 5e6) == pytest.approx(expected_k2, rel=1e-12)
    assert k2_min(THESIS, 5e6) == pytest.approx(515.9, abs=0.05)
    assert k2_min(THESIS, 5e6) != pytest.approx(567.6, abs=1.0)  # the quoted value
    e1 = (13.43 + 580) ** 3 / 3.98e-3**2
    e2 = 5e6**2 / 6.63e-3**2 * (580**2 - expected_k2**2)
    assert k0_max(THESIS, 5e6, 580) == pytest.approx(-e1 + math.sqrt(e1**2 + e2), rel=1e-9)
    assert k0_max(THESIS, 5e6, 580) == pytest.approx(1.515e9, rel=1e-3)


def test_thesis_gains_accepted():
    report = validate_gains(THESIS, k1=5e6, k2=580, k0=1e9, kA=1.5e9, f=100)
    assert report.valid and report.reasons == ()
    assert any("567.6" in note for note in report.notes)


@pytest.mark.parametrize(
    "k2, k0, fragment",
    [
        (510.0, 1e8, "k2_min"),
        (580.0, 1.6e9, "k0_max"),
        (580.0, -1.0, "must be > 0"),
        (None, 1e9, "k2 not given"),
    ],
)
def test_bad_gains_rejected_with_reason(k2, k0, fragment):
    report = validate_gains(THESIS, k1=5e6, k2=k2, k0=k0)
    assert not report.valid
    assert any(fragment in r for r in report.reasons), report.reasons


def test_k0_max_zero_below_k2_min_and_increasing_above():
    assert k0_max(THESIS, 5e6, 500.0) == 0.0
    assert 0 < k0_max(THESIS, 5e6, 520.0) < k0_max(THESIS, 5e6, 580.0)


def test_k1_must_be_positive_and_finite():
    with pytest.raises(GainError, match="k1 > 0"):
        k2_min(THESIS, 0.0)
    with pytest.raises(GainError, match="finite"):
        validate_gains(THESIS, 5e6, k2=float("nan"))


def test_bounds_errors(tmp_path):
    with pytest.raises(BoundsError, match="m_max"):
        THESIS.replace(m_max=1e-3)
    with pytest.raises(BoundsError, match="sigma_max"):
        THESIS.replace(sigma_max=0.3)
    bad = tmp_path / "b.yaml"
    bad.write_text(
        "bounds: {m_min: 1e-3, m_max: 2e-3, c_max: 1, kappa_x_max: 1, kappa_w_max: 1, "
        "sigma_max: 1}\n"
    )
    with pytest.raises(BoundsError, match="missing key.*rho_max"):
        load_bounds(bad)
    bad.write_text(
        "bounds: {m_min: 1e-3, m_max: 2e-3, c_max: 1, kappa_x_max: 1, kappa_w_max: 1, "
        "sigma_max: 1, rho_max: 1, rho_mx: 2}\n"
    )
    with pytest.raises(BoundsError, match="unknown key.*rho_mx"):
        load_bounds(bad)
    assert load_nominal_plant(bad) is None
    bad.write_text("bounds: {m_min: [1e-3\n")
    with pytest.raises(BoundsError, match="b.yaml is not valid YAML"):
        load_bounds(bad)
    with pytest.raises(BoundsError, match="cannot read bounds file .*missing.yaml"):
        load_bounds(tmp_path / "missing.yaml")
