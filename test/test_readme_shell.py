"""The README's shell blocks as a tested contract: every command of every ```bash block of
README.md is either run here as written, with what the README says of it checked (an output it
shows, a result it names, an exit code or a one-line refusal it states), or listed in EXCLUDED
with the reason it cannot run here; a test checks that the two tables and the README name the
same commands, so neither list goes stale silently.

Where the commands run: a fresh folder laid out like the repository root (bags/, config/,
test/, scripts/, bench/, .venv/ and install/ linked to the repository's), shared by the blocks
in README order (a later block uses what an earlier one wrote: params.yaml, p885.yaml, my_run);
what they write stays there, the repository is not touched. Inputs the README presumes the
reader has (an oscilloscope's run_0_300V.csv, a sine_run.csv, my_rig_bounds.yaml, ...) are made
from the repository's data by ``_inputs`` and named in PLACEHOLDERS.

A command that serves until Ctrl-C (a launch, record, view) is started, waited for until the
line that says it is up (``ready``), left running ``serve`` seconds (beside another serving
command when ``beside`` says so) and stopped with SIGINT to its process group, as a terminal's
Ctrl-C does; it must then exit as the README says (0: "stops everything cleanly on Ctrl-C").

Long runs: every command gets ``PIEZO_QUICK=1`` in its environment (README, "Commission your
rig"): the commands that take minutes shorten themselves (the same arguments, fewer periods or
sweep frequencies). A command whose figures are the host's timing (a learning loop on the
emulated rig or scanner in real time) is excluded and named with the test that runs it alone
(the serial phase of ``make test``). Budget: about five minutes on 2 cores.

The layer is ``ros`` and ``slow``, one file (the blocks share their folder and run in order,
on one worker: ``--dist loadfile``) beside the other worker's tests; what runs in real time
here (a launch of the emulators, ``identify --device`` on the E-727 emulator) times itself by
the emulated device's clock, not by the host's.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from piezo_stage.commands.quick import QUICK_VARIABLE

pytestmark = [pytest.mark.ros, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
QUICK = QUICK_VARIABLE
LINKED = ("bags", "config", "test", "scripts", "bench", ".venv", "install")


# --- the README's shell blocks -----------------------------------------------------------------
@dataclass(frozen=True)
class Command:
    line: int  # README line of its first line
    text: str  # as written (continuation lines joined), comments kept
    key: str  # without its comment, whitespace collapsed: the tables' key


def _strip_comment(text: str) -> str:
    out, quote = [], ""
    for i, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or text[i - 1].isspace()):
            break
        out.append(ch)
    return " ".join("".join(out).split())


def readme_blocks(text: str | None = None) -> list[tuple[int, list[Command]]]:
    """``(line, commands)`` of every ```bash block, in README order: one command per logical
    line (a trailing backslash continues it), comment-only lines dropped."""
    text = README.read_text(encoding="utf-8") if text is None else text
    blocks = []
    for match in re.finditer(r"^```bash\n(.*?)^```", text, re.S | re.M):
        first = text[: match.start(1)].count("\n") + 1
        commands, pending, start = [], "", 0
        for k, raw in enumerate(match.group(1).splitlines()):
            if not pending:
                start = first + k
            if raw.rstrip().endswith("\\"):
                pending += raw.rstrip()[:-1] + " "
                continue
            whole, pending = pending + raw, ""
            key = _strip_comment(whole)
            if key:
                commands.append(Command(start, " ".join(whole.split()), key))
        blocks.append((first, commands))
    return blocks


# --- what is run, what is not ----------------------------------------------------------------
Check = Callable[[str, Path, dict], None]


@dataclass(frozen=True)
class Expect:
    code: int = 0  # exit code (of the stop, for a command that serves)
    out: tuple[str, ...] = ()  # regexes its output (stdout + stderr) must match
    files: tuple[str, ...] = ()  # globs it must leave in the folder
    ready: str | None = None  # serves until Ctrl-C: the regex of the line that says it is up
    serve: float = 2.0  # seconds it serves after `ready` before the Ctrl-C
    beside: str | None = None  # a README command serving meanwhile (key of RUN)
    check: Check | None = None  # a further check (output, folder, results so far)
    timeout: float = 240.0


def _identified(out: str, folder: Path, results: dict) -> None:
    """`identify BAG --json`: the analytic method, the true parameters of bags/README.md."""
    got = json.loads(out[out.index("{") :])
    assert got["method"] == "analytic", got
    true = {"rho": 0.0047, "sigma": 0.812, "n": 1.12, "kappa_w": 9.22e-6}
    for name, value in true.items():
        assert got[name] == pytest.approx(value, rel=2e-3), name
    results["identify ch10"] = got


def _coupled(out: str, folder: Path, results: dict) -> None:
    """`experiment coupling --graph sim_scanner` (lockstep) on the shipped XY stage: every
    axis's Bouc-Wen part within 2 % of the stage's (κx in V/µm and ρ in 1/µm as printed), the
    coupling within 5 % of its off-diagonal terms, and the stage file it wrote loads."""
    from piezo_stage.model.stage_file import load_stage

    got = json.loads(out[out.index("{") :])
    truth = load_stage(ROOT / "config" / "xy_scanner.yaml")
    for axis in truth.axes:
        fitted, model = got["axes"][axis.name], axis.model.bouc_wen
        assert fitted["kappa"][0] * 1e6 == pytest.approx(model.kappa[0], rel=0.02), axis.name
        assert fitted["rho"] * 1e6 == pytest.approx(model.rho, rel=0.02), axis.name
        for name in ("kappa_w", "sigma", "n"):
            assert fitted[name] == pytest.approx(getattr(model, name), rel=0.02), name
    off = ~np.eye(len(truth.axes), dtype=bool)
    coupling = np.array(got["coupling"])
    assert np.abs(coupling - truth.coupling)[off].max() <= 0.05 * np.abs(truth.coupling[off]).min()
    assert load_stage(folder / "my_scanner.yaml").names == truth.names


def _commissioned(out: str, folder: Path, results: dict) -> None:
    """`commission out/ --json` on the sim graph's folder: my_plant.yaml is a plant the
    procedure does not know (PLACEHOLDERS): its Bouc-Wen part within 2 %, m and c within 10 %,
    bounds that hold it, gains inside Theorem 4's, the loop stable and u kept within 1 % after the
    perturbation; the files and one bag per run (the sweep at 50 and 100 Hz)."""
    from piezo_stage.model.parameter_set import load_parameter_set

    s, _ = json.JSONDecoder().raw_decode(out[out.index("{") :])  # stderr's lines may follow
    plant = load_parameter_set(folder / "my_plant.yaml")
    p, dynamics = plant.bouc_wen, plant.dynamics
    assert dynamics is not None
    truth = {
        "kappa_x": p.kappa[0],
        "kappa_w": p.kappa_w,
        "rho": p.rho,
        "sigma": p.sigma,
        "n": p.n,
        "m": dynamics.m,
        "c": dynamics.c,
    }
    for key in ("kappa_x", "kappa_w", "rho", "sigma", "n"):
        assert s["identified"][key] == pytest.approx(truth[key], rel=0.02), key
    for key in ("m", "c"):
        assert s["identified"][key] == pytest.approx(truth[key], rel=0.10), key
    b = s["bounds"]
    assert b["m_min"] < truth["m"] < b["m_max"] and b["c_max"] > truth["c"]
    for key in ("kappa_x", "kappa_w", "sigma", "rho"):
        assert b[f"{key}_max"] > truth[key], key
    assert s["gains"]["k2"] > s["k2_min"] and 0 < s["gains"]["k0"] < s["k0_max"]
    assert s["spectral_radius"] < 1.0
    assert s["closed_loop"]["u_change_relative"] <= 0.01
    for key in ("parameter_set", "bounds", "controller", "report"):
        assert Path(s["files"][key]).is_file()
    assert sorted(p.name for p in (folder / "out" / "bags").iterdir()) == [
        "acceptance",
        "dynamics_step",
        "sweep_100Hz",
        "sweep_50Hz",
    ]


def _replayed(out: str, folder: Path, results: dict) -> None:
    """The replay "gives the same numbers as `piezo-stage identify` on the bag, to the last
    digit"."""
    import yaml

    offline = results.get("identify ch10")
    assert offline is not None, "the README's `identify bags/ch10_identification` did not run"
    got = yaml.safe_load((folder / "replayed.yaml").read_text())["bouc_wen"]
    assert got["kappa"] == pytest.approx(offline["kappa"], rel=1e-9)
    for name in ("y0", "kappa_w", "rho", "sigma", "n"):
        assert got[name] == pytest.approx(offline[name], rel=1e-9), name


def _theorem4(out: str, folder: Path, results: dict) -> None:
    """The README: "(11.6) k2_min, (11.7) k0_max: 515.9 and 1.515e9 with the thesis bounds"."""
    k2 = float(re.search(r"k2_min = (\S+)", out).group(1))  # type: ignore[union-attr]
    k0 = float(re.search(r"k0_max = (\S+)", out).group(1))  # type: ignore[union-attr]
    assert (f"{k2:.1f}", f"{k0:.4g}") == ("515.9", "1.515e+09"), (k2, k0)


def _unstable_at_20khz(out: str, folder: Path, results: dict) -> None:
    """The README: the thesis gains' sampled loop is "unstable at 5-50 kHz"."""
    got = json.loads(out[out.index("{") :])
    text = json.dumps(got)
    assert re.search(r'"stable": false', text), text[:2000]


def _exports(out: str, folder: Path, results: dict) -> None:
    """The README: "one CSV per topic, SI units in the headers"."""
    files = sorted((folder / "my_run_csv").glob("*.csv"))
    assert files, out
    headers = [f.read_text().splitlines()[0] for f in files]
    assert any("[V]" in h for h in headers) and any("[m]" in h for h in headers), headers


#: a stage the README runs, beside which `view` and `record` run
SIM_CLOSED_LOOP = (
    "piezo-stage launch sim_closed_loop --param controller.mode:=pid_sine "
    "--param plant.rate_hz:=1000.0"
)

RUN: dict[str, Expect] = {
    # set-up shell
    "source scripts/env.sh": Expect(),
    'python -c "import rclpy, piezo_stage_msgs.msg"': Expect(),
    "piezo-stage --help": Expect(out=(r"\blaunch\b", r"\bidentify\b", r"\bcommission\b")),
    # running graphs: each until it is ready, then Ctrl-C
    "piezo-stage launch sim_identification": Expect(ready=r"\[launch\] +ready after"),
    "piezo-stage launch sim_identification --ns /stage2": Expect(
        ready=r"\[launch\] +ready after", beside="piezo-stage launch sim_identification"
    ),
    SIM_CLOSED_LOOP: Expect(ready=r"\[launch\] +ready after"),
    "piezo-stage launch sim_closed_loop --param controller.reference:=15e-6": Expect(
        ready=r"\[launch\] +ready after"
    ),
    # identify from recordings
    "piezo-stage identify run_0_300V.csv run_100_400V.csv --degree 2 --output params.yaml": Expect(
        out=(r"analytic",), files=("params.yaml",)
    ),
    "piezo-stage identify bags/ch10_identification --degree 2 --json": Expect(check=_identified),
    "piezo-stage validate params.yaml sine_run.csv --out plots/": Expect(
        out=(r"(?i)rms",), files=("plots/*.png",)
    ),
    "piezo-stage identify test/data/p885/p885_raised_cosine.csv --degree 2 --output p885.yaml": (
        Expect(
            out=(r"method fit", r"delay"),
            files=("p885.yaml",),
        )
    ),
    "piezo-stage validate p885.yaml other_run.csv": Expect(out=(r"(?i)rms",)),
    "piezo-stage identify bags/ch10_identification --source cycles --degree 2": Expect(
        out=(r"from 2 limit cycle\(s\) on /piezo/limit_cycles", r"method analytic")
    ),
    "piezo-stage launch replay_cycles --param identifier.output_file:=$PWD/cycles.yaml": Expect(
        out=(r"holding limit cycle at offset 100", r"identifier exited with code 0"),
        files=("cycles.yaml",),
        timeout=600,
    ),
    # PI controllers: play and record in the controller
    "piezo-stage emulate e727 --tcp 50000": Expect(ready=r"^e727: tcp://127\.0\.0\.1:50000"),
    "piezo-stage identify --device tcp://127.0.0.1:50000 --axis 1 --model-input displacement "
    "--output pi_axis1.yaml --bag pi_axis1": Expect(
        beside="piezo-stage emulate e727 --tcp 50000",
        out=(
            r"8 settling periods instead of 16",
            r"recorded 560000 points at 20 kHz",
            r"method analytic",
        ),
        files=("pi_axis1.yaml", "pi_axis1/metadata.yaml"),
        timeout=300,
    ),
    "piezo-stage identify pi_axis1 --input-topic /piezo/displacement --output-topic "
    "/piezo/voltage --steady-periods 6 --lag 0.5": Expect(out=(r"method analytic",)),
    "piezo-stage experiment tracking --graph pi_servo --device tcp://127.0.0.1:50000 --axis 1 "
    "--trajectory triangle --frequency 100 --amplitude 5e-6 --offset 5e-6 --model ch11_rig.yaml "
    "--table-out pi_table.json --json": Expect(
        beside="piezo-stage emulate e727 --tcp 50000",
        out=(r'"rms_relative"', r'"rate_hz": 20000', r'"at_limit_points": 0'),
        files=("pi_table.json",),
    ),
    "piezo-stage launch pi_rig_loop": Expect(ready=r"\[launch\] +ready after"),
    # a raster in the controller
    "piezo-stage emulate e727 --tcp 50001 --stage xy_scanner.yaml": Expect(
        ready=r"^e727: tcp://127\.0\.0\.1:50001"
    ),
    "piezo-stage experiment raster --graph pi_servo --device tcp://127.0.0.1:50001 --stage "
    "xy_scanner.yaml --lines 64 --pixels 256 --line-rate 200 --range 8e-6,8e-6 --centre "
    "5e-6,5e-6 --learn 20 --table-out pi_scan.json --json": Expect(
        beside="piezo-stage emulate e727 --tcp 50001 --stage xy_scanner.yaml",
        out=(r'"graph": "pi_servo"', r'"rate_hz": 20000', r'"frame_wall"'),
        files=("pi_scan.json",),
    ),
    # gains
    "piezo-stage gains --k1 5e6 --k2 580 --k0 1e9 --rate-hz 1000": Expect(
        out=(r"STABLE",), check=_theorem4
    ),
    "piezo-stage gains --bounds my_rig_bounds.yaml --k1 5e6 --rate-hz 20000 --delay-samples 1 "
    "--json": Expect(code=1, check=_unstable_at_20khz),
    "piezo-stage gains --k1 5e6 --law smc --rate-hz 1000 --delay-samples 1": Expect(
        out=(r"ks = 53\.614", r"phi = 0\.32\d*", r"phi designed", r"STABLE", r"gains VALID")
    ),
    "piezo-stage gains --k1 5e6 --law adaptive --rate-hz 1000": Expect(
        out=(r"tau_a = 0\.218\d*", r"kx_max = 1\.08e\+07", r"tau_a designed", r"gains VALID")
    ),
    # commissioning: minutes of simulated stage each
    "piezo-stage commission out/ --param plant.model_file:=my_plant.yaml": Expect(
        out=(r"PIEZO_QUICK=1: the sweep at 50, 100 Hz only",),
        files=("out/report.md", "out/controller.yaml"),
        timeout=1800,
    ),
    "piezo-stage commission out/ --json": Expect(check=_commissioned),
    # tracking
    "piezo-stage experiment tracking --trajectory triangle --amplitude 10e-6 --frequency 10 "
    "--compensation both --identify-model model.yaml --compare --png plots/ --json": Expect(
        out=(r'"rms_relative"', r"PIEZO_QUICK=1: 2 periods instead of 3", r'"quick": true'),
        files=("model.yaml",),
        timeout=1800,
    ),
    "piezo-stage experiment tracking --trajectory sine --amplitude 5e-6 --frequency 100 "
    "--model model.yaml": Expect(timeout=1800),
    "piezo-stage experiment tracking --trajectory scan.csv --model model.yaml "
    "--plant-model other_rig.yaml": Expect(timeout=1800),
    "piezo-stage experiment tracking --rate-hz 1000 --learn 20 --model model.yaml "
    "--table-out scan.json --png plots/ --json": Expect(files=("scan.json",), timeout=1800),
    "piezo-stage experiment tracking --rate-hz 1000 --table scan.json --model model.yaml": Expect(
        timeout=1800
    ),
    # "refused: the gains fail the sampled-loop check at 10 kHz (exit 2)"
    "piezo-stage experiment tracking --rate-hz 10000 --model model.yaml": Expect(
        code=2, out=(r"(?i)sampled", r"10000|10 kHz")
    ),
    # two and three axes
    "piezo-stage launch sim_scanner": Expect(ready=r"\[launch\] +ready after"),
    "piezo-stage launch sim_scanner --stage xyz_scanner.yaml --ns /xyz": Expect(
        ready=r"\[launch\] +ready after"
    ),
    "piezo-stage experiment coupling --graph sim_scanner --plant-stage xy_scanner.yaml "
    "--output my_scanner.yaml --json": Expect(check=_coupled, timeout=900),
    "piezo-stage emulate scanner --stage xy_scanner.yaml --log applied.csv": Expect(
        ready=r"^scanner: ", files=("applied.csv",)
    ),
    "piezo-stage launch emulated_scanner --stage xyz_scanner.yaml": Expect(
        ready=r"\[launch\] +ready after"
    ),
    "piezo-stage launch emulated_scanner_loop": Expect(ready=r"\[launch\] +ready after"),
    # shared networks: exports in the block's own shell
    "export ROS_DOMAIN_ID=42": Expect(),
    "export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST": Expect(),
    "export ROS_AUTOMATIC_DISCOVERY_RANGE=OFF": Expect(),
    'export ROS_STATIC_PEERS="192.168.0.20;192.168.0.21"': Expect(),
    # the live view
    "piezo-stage launch sim_closed_loop --view": Expect(
        ready=r"\[launch\] +ready after", out=(r"ws://127\.0\.0\.1:8765",)
    ),
    "piezo-stage view --ns /piezo": Expect(
        ready=r"Foxglove live view on ws://127\.0\.0\.1:8765",
        beside=SIM_CLOSED_LOOP,
    ),
    "piezo-stage view --ns /stage2 --write-layout stage2.json": Expect(
        out=(r"wrote .*stage2\.json",), files=("stage2.json",)
    ),
    # record and replay: record beside a running stage, Ctrl-C finalises the bag
    "piezo-stage record --ns /piezo -o my_run": Expect(
        ready=r"recording /piezo",
        serve=5.0,
        beside=SIM_CLOSED_LOOP,
        out=(r"bag: .*my_run",),
        files=("my_run/metadata.yaml",),
    ),
    "piezo-stage bag info my_run": Expect(out=(r"Messages:", r"/piezo/displacement")),
    "piezo-stage bag export my_run --csv my_run_csv": Expect(check=_exports),
    "piezo-stage play my_run --clock --rate 2": Expect(),
    "piezo-stage bag reindex my_run": Expect(),
    "piezo-stage plot my_run --out plots/": Expect(files=("plots/*.png",)),
    "piezo-stage launch replay_identification --param "
    "player.bag:=$PWD/bags/ch10_identification --param identifier.degree:=2 "
    "--param identifier.output_file:=$PWD/replayed.yaml": Expect(
        out=(r"played (\d+) of \1 messages", r"identifier exited with code 0"),
        files=("replayed.yaml",),
        check=_replayed,
        timeout=900,
    ),
}

#: commands that cannot run here, and why (each must still be in the README)
EXCLUDED: dict[str, str] = {
    "make demo": "the whole demo (3-4 min, after `make setup`): test/test_demo.py runs its stages",
    "make test": "runs every test, this layer included",
    "make test-fast": "the unit layer, which `make test` runs itself",
    "make fuzz": "the property tests with 50x their examples: not in CI by design",
    "source /opt/ros/jazzy/setup.bash": "Ubuntu 24.04 with apt-installed ROS 2 (not here)",
    "sudo apt install python3-scipy python3-serial python3-matplotlib python3-yaml": (
        "Ubuntu's apt, as root"
    ),
    "pip install --break-system-packages mcap mcap-ros2-support rosbags": (
        "installs into the system Python of the Ubuntu set-up"
    ),
    "cd piezo_stage": "the Ubuntu set-up's clone of the repository",
    "colcon build": "the Ubuntu set-up's colcon build (this machine builds with make setup)",
    "source install/setup.bash": "the Ubuntu set-up's colcon install",
    "ros2 run piezo_stage plant --ros-args -p model_file:=ch10_patch.yaml "
    "-p clock_mode:=realtime": "needs the Ubuntu set-up's `ros2` CLI (no ros2cli wheel here)",
    "piezo-stage launch rig_loop --param voltage_driver.url:=tcp://192.168.0.20:50000 "
    "--param laser_reader.url:=/dev/ttyUSB1 --param controller.start_closed:=true": (
        "a real rig: an amplifier at 192.168.0.20 and a laser on /dev/ttyUSB1"
    ),
    "python bench/control_loop.py": (
        "a benchmark (minutes, the whole CPU): its figures are measured on a quiet machine"
    ),
    "python bench/tracking.py": "a benchmark: its figures are measured on a quiet machine",
    "python bench/laws.py": (
        "a benchmark that states targets (exit 1 where one is missed): test/test_control_"
        "sliding.py checks the sliding-mode law's parts and its perturbation in the core"
    ),
    "piezo-stage launch rig_scanner --stage my_scanner.yaml "
    "--param voltage_driver.url:=tcp://192.168.0.21:50000": (
        "a real scanner: an amplifier at 192.168.0.21 and sensors (config/rig_devices.yaml)"
    ),
    "piezo-stage launch rig_loop --stage my_scanner.yaml": (
        "a real scanner: its amplifier and sensors (config/rig_devices.yaml)"
    ),
    "python bench/scanner.py": "a benchmark: its figures are measured on a quiet machine",
    "python bench/staircase.py": "a benchmark: its figures are measured on a quiet machine",
    "python bench/scanner_loop.py": "a benchmark: its figures are measured on a quiet machine",
    "piezo-stage experiment coupling --graph emulated_scanner --output emulated_scanner.yaml": (
        "the emulated scanner's seven processes in real time want more than this 2-core "
        "host: run alone it completes 4 of 7 runs here (the README says why)"
    ),
    "piezo-stage experiment raster --stage xy_scanner.yaml --lines 64 --pixels 256 "
    "--line-rate 10 --rate-hz 8000 --learn 20 --table-out scan_tables.json --png scan/ "
    "--json": (
        "three 8 kHz frames of 64 lines (15 s of CPU here, 40 s beside the workers): "
        "test/test_experiment_raster.py runs the same command, learning, tables and PNGs, on a "
        "small scan"
    ),
    "piezo-stage experiment raster --stage xy_scanner.yaml --table scan_tables.json --json": (
        "replays the tables of the command before it (not run): test/test_experiment_raster.py "
        "replays tables"
    ),
    "python bench/raster.py": "a benchmark: its figures are measured on a quiet machine",
    "piezo-stage experiment raster --graph sim_scanner --stage xy_scanner.yaml --lines 8 "
    "--pixels 64 --line-rate 2 --learn 8 --json": (
        "test/test_experiment_raster_sim.py runs a smaller scan through the same nodes, against "
        "the core and twice (the same numbers), learning checked"
    ),
    "piezo-stage experiment raster --lines 16 --pixels 64 --view": (
        "the view on port 8765: test/test_raster_view.py runs a small raster with its view on "
        "a free port and checks the image a Foxglove client receives against the run's bag"
    ),
    "piezo-stage experiment raster --graph emulated_scanner --lines 8 --pixels 128 "
    "--line-rate 2 --learn 20 --bag scan_bag --json": (
        "the emulated scanner's processes in real time: test/test_experiment_raster_emulated.py "
        "runs it alone (the serial phase), bag and learning checked"
    ),
    "piezo-stage experiment raster --graph rig_scanner --stage my_scanner.yaml --lines 64 "
    "--pixels 128 --line-rate 2 --learn 20 --png scan/": (
        "a real scanner: its amplifier and sensors (config/rig_devices.yaml)"
    ),
    "piezo-stage experiment tracking --graph emulated_rig --learn 20 --model model.yaml --json": (
        "the emulated rig in real time: test/test_emulated_rig_tracking.py runs it alone (the "
        "serial phase), learning, the saved table and its replay checked"
    ),
    "piezo-stage commission emulated/ --graph emulated_rig --m 5.3e-3 --c 13": (
        "the emulators in real time: test/test_commission_ros.py runs it alone (the serial "
        "phase, one sweep frequency) and checks its model, bounds, gains and perturbation"
    ),
    "piezo-stage commission rig/ --graph rig --m 5.3e-3 --c 13 --m-std 2e-4": (
        "a real rig's devices (config/rig_devices.yaml)"
    ),
}

#: files the README presumes its reader has, made by _inputs from the repository's data
PLACEHOLDERS = {
    "run_0_300V.csv": "run 0 of bags/ch10_identification (0-300 V), time/input/output in SI",
    "run_100_400V.csv": "run 1 of bags/ch10_identification (100-400 V)",
    "sine_run.csv": "the ch. 10 patch simulated under a 0.1 Hz sine of 50-350 V",
    "other_run.csv": "test/data/p885/p885_raised_cosine.csv again (the P-885's only record)",
    "my_rig_bounds.yaml": "config/thesis_rig_bounds.yaml",
    "my_plant.yaml": "config/ch11_rig.yaml, κw +20 % and m -15 %: a plant unknown to commission",
    "other_rig.yaml": "config/ch11_rig.yaml",
    "scan.csv": "two periods of a 10 Hz sine of 10 µm from 6 µm up, as `t [s], x [m]`",
    "model.yaml": "config/ch11_rig.yaml, until `--identify-model` writes it",
}

BLOCKS = readme_blocks()


def test_every_readme_command_is_run_or_excluded_with_its_reason():
    """The tables and the README part as soon as a command is added, changed or removed."""
    in_readme = [c.key for _, commands in BLOCKS for c in commands]
    both = sorted(set(RUN) & set(EXCLUDED))
    assert not both, f"both run and excluded: {both}"
    missing = [k for k in in_readme if k not in RUN and k not in EXCLUDED]
    assert not missing, f"README commands neither run nor excluded (add them to RUN): {missing}"
    stale = sorted(k for k in [*RUN, *EXCLUDED] if k not in in_readme)
    assert not stale, f"commands the tables name but the README no longer has: {stale}"
    for key, expect in RUN.items():
        if expect.beside is not None:
            assert expect.beside in RUN and RUN[expect.beside].ready, key


def test_the_block_parser_joins_continuations_and_drops_comments():
    text = "x\n```bash\n# note\na --b \\\n    --c   # said\nd '#no'  # yes\n```\n"
    [(line, commands)] = readme_blocks(text)
    assert line == 3 and [c.key for c in commands] == ["a --b --c", "d '#no'"]
    assert commands[0].line == 4 and commands[1].line == 6


# --- running them ------------------------------------------------------------------------------
def _write_csv(path: Path, t, u, y) -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time [s]", "input [V]", "output [m]"])
        w.writerows(zip(t, u, y))


def _inputs(folder: Path) -> None:
    import numpy as np

    from piezo_stage.identification import load_runs
    from piezo_stage.model import StaticPlant, shipped_parameter_set
    from piezo_stage.model.parameter_set import save_parameter_set

    runs = load_runs([ROOT / "bags" / "ch10_identification"])
    for run, name in zip(runs, ("run_0_300V.csv", "run_100_400V.csv")):
        _write_csv(folder / name, run.t, run.input, run.output)
    t = np.arange(0.0, 30.0, 0.02)
    v = 200.0 - 150.0 * np.cos(2 * np.pi * 0.1 * t)
    y = StaticPlant(shipped_parameter_set("ch10_patch").bouc_wen).simulate(v)
    _write_csv(folder / "sine_run.csv", t, v, y)
    shutil.copy(ROOT / "test/data/p885/p885_raised_cosine.csv", folder / "other_run.csv")
    shutil.copy(ROOT / "config/thesis_rig_bounds.yaml", folder / "my_rig_bounds.yaml")
    for name in ("other_rig.yaml", "model.yaml"):
        shutil.copy(ROOT / "config/ch11_rig.yaml", folder / name)
    rig = shipped_parameter_set("ch11_rig")
    assert rig.dynamics is not None
    unknown = replace(
        rig,
        name="my_plant",
        bouc_wen=replace(rig.bouc_wen, kappa_w=1.2 * rig.bouc_wen.kappa_w),
        dynamics=replace(rig.dynamics, m=0.85 * rig.dynamics.m),
    )
    save_parameter_set(unknown, folder / "my_plant.yaml")
    # from 6 µm up: the experiments' floor, where the 0-400 V amplifier still has its margin
    ts = np.arange(0.0, 0.2, 1e-3)
    with (folder / "scan.csv").open("w") as f:
        f.write("t [s], x [m]\n")
        f.writelines(f"{a:.6f}, {6e-6 + 5e-6 * (1 - np.cos(2 * np.pi * 10 * a)):.9e}\n" for a in ts)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """The repository root's stand-in: its read-only folders linked, its outputs kept apart."""
    path = tmp_path_factory.mktemp("readme")
    for name in LINKED:
        (path / name).symlink_to(ROOT / name)
    _inputs(path)
    return path


RESULTS: dict = {}


class _Running:
    """A command serving in its own process group, its output collected line by line."""

    def __init__(self, text: str, folder: Path, env: dict[str, str]) -> None:
        self.lines: list[str] = []
        self.proc = subprocess.Popen(
            ["bash", "-c", text],
            cwd=folder,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def wait_for(self, pattern: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if re.search(pattern, self.output, re.M):
                return True
            if self.proc.poll() is not None:
                self._reader.join(5.0)
                return bool(re.search(pattern, self.output, re.M))
            time.sleep(0.1)
        return False

    def wait_exit(self, timeout: float) -> bool:
        """Whether it ended by itself within ``timeout``, its output then read to the end."""
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return False
        self._reader.join(5.0)
        return True

    def stop(self, timeout: float = 60.0) -> int:
        """Ctrl-C (SIGINT to the group); SIGKILL if it outlives ``timeout``."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10.0)
        self._reader.join(5.0)
        return self.proc.returncode


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env[QUICK] = "1"
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def _run(command: Command, expect: Expect, folder: Path) -> str:
    env = _env()
    where = f"README.md:{command.line}: {command.text}"
    helper = None
    try:
        if expect.beside is not None:  # a README command serving meanwhile
            helper = _Running(expect.beside, folder, env)
            ready = RUN[expect.beside].ready
            assert ready and helper.wait_for(ready, expect.timeout), helper.output[-3000:]
        if expect.ready is None:
            running = _Running(command.text, folder, env)
            ended = running.wait_exit(expect.timeout)
            code = running.stop()  # a command still running after its time: what it said
            out = running.output
            assert ended, f"{where}: still running after {expect.timeout:g} s:\n{out[-3000:]}"
        else:
            running = _Running(command.text, folder, env)
            try:
                up = running.wait_for(expect.ready, expect.timeout)
                if up:
                    time.sleep(expect.serve)
            finally:
                code = running.stop()
            out = running.output
            assert up, f"{where}: never said {expect.ready!r}:\n{out[-3000:]}"
    finally:
        if helper is not None:
            helper.stop()
    assert code == expect.code, f"{where}: exit code {code}, not {expect.code}:\n{out[-3000:]}"
    for pattern in expect.out:
        assert re.search(pattern, out, re.M), f"{where}: no {pattern!r} in:\n{out[-3000:]}"
    for pattern in expect.files:
        assert list(folder.glob(pattern)), f"{where}: left no {pattern}:\n{out[-3000:]}"
    if expect.check is not None:
        expect.check(out, folder, RESULTS)
    return out


@pytest.mark.parametrize(
    "commands", [pytest.param(c, id=f"README.md:{line}") for line, c in BLOCKS]
)
def test_readme_block(commands: list[Command], folder: Path):
    """Each command of the block in order, in the shared folder: as the README says, or the
    reason it is not run (EXCLUDED) reported as this block's skip."""
    not_run = []
    for command in commands:
        if command.key in EXCLUDED:
            not_run.append(f"line {command.line} `{command.key}`: {EXCLUDED[command.key]}")
            continue
        assert command.key in RUN, f"README.md:{command.line}: {command.key!r} is in no table"
        _run(command, RUN[command.key], folder)
    if not_run:
        pytest.skip("not run: " + "; ".join(not_run))
