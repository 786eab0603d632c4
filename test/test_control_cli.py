"""`piezo-stage gains`: table, JSON, overrides, exit codes."""

import json

import pytest

from piezo_stage.cli import main

pytestmark = pytest.mark.unit


def gains(capsys, *argv):
    code = main(["gains", *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_json_thesis_gains_with_rate(capsys):
    code, out, _ = gains(
        capsys,
        "--k1",
        "5e6",
        "--k2",
        "580",
        "--k0",
        "1e9",
        "--rate-hz",
        "1000",
        "--delay-samples",
        "1",
        "--json",
    )
    data = json.loads(out)
    assert code == 0
    assert data["k2_min"] == pytest.approx(515.875, abs=1e-3)
    assert data["k0_max"] == pytest.approx(1.5146e9, rel=1e-4)
    assert (data["k0"], data["k1"], data["k2"]) == (1e9, 5e6, 580)
    assert data["valid"] is True and data["reasons"] == []
    disc = data["discrete"]
    assert disc["rate_hz"] == 1000 and disc["delay_samples"] == 1 and disc["stable"] is True
    assert disc["spectral_radius"] == pytest.approx(0.9319, abs=1e-4)
    assert disc["margin"] == pytest.approx(1 - disc["spectral_radius"])


def test_json_unstable_rate_exit_1(capsys):
    code, out, _ = gains(
        capsys, "--k1", "5e6", "--k2", "580", "--k0", "1e9", "--rate-hz", "20000", "--json"
    )
    data = json.loads(out)
    assert code == 1 and data["valid"] is True and data["discrete"]["stable"] is False


def test_json_without_rate_and_invalid_k0(capsys):
    code, out, _ = gains(capsys, "--k1", "5e6", "--k2", "580", "--k0", "2e9", "--json")
    data = json.loads(out)
    assert code == 1 and data["valid"] is False and data["discrete"] is None
    assert any("k0_max" in r for r in data["reasons"])


def test_bound_override_changes_k2_min(capsys):
    _, out, _ = gains(capsys, "--k1", "5e6", "--m-max", "8e-3", "--json")
    assert json.loads(out)["k2_min"] == pytest.approx(515.875 * (8e-3 / 6.63e-3) ** 0.5, rel=1e-6)


def test_human_table(capsys):
    code, out, _ = gains(capsys, "--k1", "5e6", "--k2", "580", "--k0", "1e9", "--rate-hz", "5000")
    assert code == 1
    assert "k2_min = 515.875" in out and "VALID" in out and "UNSTABLE" in out and "567.6" in out


def test_bad_input_exit_2(capsys, tmp_path):
    code, _, err = gains(capsys, "--k1", "5e6", "--k2", "500", "--rate-hz", "1000")
    assert code == 2 and "no admissible gains" in err and "k2_min" in err  # no k0 exists
    flat = tmp_path / "b.yaml"
    flat.write_text(
        "m_min: 1e-3\nm_max: 2e-3\nc_max: 1\nkappa_x_max: 1e6\nkappa_w_max: 1\nsigma_max: 1\n"
        "rho_max: 1\n"
    )
    code, _, err = gains(
        capsys, "--bounds", str(flat), "--k1", "1e6", "--k2", "200", "--k0", "1", "--rate-hz", "1e3"
    )
    assert code == 2 and "nominal" in err
    code, out, _ = gains(
        capsys,
        "--bounds",
        str(flat),
        "--k1",
        "1e6",
        "--k2",
        "200",
        "--k0",
        "1",
        "--rate-hz",
        "1e3",
        "--m",
        "1e-3",
        "--c",
        "1",
        "--kappa-x",
        "1e6",
        "--json",
    )
    assert code in (0, 1) and json.loads(out)["discrete"]["rate_hz"] == 1000
    code, _, err = gains(capsys, "--k1", "-1")
    assert code == 2 and "k1 > 0" in err


def test_kA_is_spelled_as_the_parameter_and_ka_still_works(capsys):
    args = ("--k1", "5e6", "--k2", "580", "--k0", "1e9", "--f", "100", "--json")
    code_a, out_a, err_a = gains(capsys, *args, "--kA", "2e9")
    code_b, out_b, _ = gains(capsys, *args, "--ka", "2e9")
    assert code_a == code_b and out_a == out_b, err_a
    assert json.loads(out_a)["kA"] == 2e9
