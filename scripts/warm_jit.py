"""Compile the model's numba kernels into their on-disk cache (piezo_stage/model/__pycache__).

A fresh clone has no cache: each process that first simulates or identifies compiles the
kernels itself (about 20 s of CPU on a 2-core host), and the first nodes and tests of a run
all do it at once. ``make setup`` runs this once, so that they load the cache instead. It
calls the paths the nodes take (simulated stage, plants, feedforward, limit cycle,
identification) with the argument types they use; what it misses still compiles on first use.
"""

from __future__ import annotations

import time

import numpy as np


def main() -> int:
    start = time.monotonic()
    from piezo_stage.control.feedforward import Feedforward, FeedforwardModel
    from piezo_stage.identification.methods import identify_runs
    from piezo_stage.identification.recording import Recording
    from piezo_stage.model import DynamicPlant, StaticPlant, limit_cycle, t_wave_pair
    from piezo_stage.model.parameter_set import shipped_parameter_set
    from piezo_stage.model.stage import SimulatedStage

    for name in ("ch9_example", "ch11_rig"):
        ps = shipped_parameter_set(name)
        stage = SimulatedStage(ps)
        stage.step(10.0, 1e-3)
        stage.step_many(np.linspace(0.0, 50.0, 20), 1e-3)
        if ps.dynamics is not None:
            plant = DynamicPlant(ps.bouc_wen, ps.dynamics)
            plant.simulate(np.linspace(0.0, 50.0, 20), 1e-3)
            plant.step(5.0, 1e-3)
            ff = Feedforward(FeedforwardModel.from_parameter_set(ps))
            ff.seed(0.0, 0.0)
            ff.step(1e-6, 0.0, 0.0)
        static = StaticPlant(ps.bouc_wen)
        static.simulate(np.linspace(0.0, 50.0, 20))
        static.step(1.0)
        bw = ps.bouc_wen
        limit_cycle(bw.rho, bw.sigma, bw.n, 0.0, 1.0, np.linspace(0.0, 1.0, 5))
    ps = shipped_parameter_set("ch9_example")
    t = np.arange(0.0, 4.0, 1e-3)
    runs = []
    for i, v in enumerate(t_wave_pair(t, 1.0, 0.0, 1.0, 0.1)):
        y = StaticPlant(ps.bouc_wen).simulate(v)
        runs.append(Recording(t, v, y, name=f"run {i}", meta={"offset": 0.1 * i}))
    try:
        identify_runs(runs)
    except Exception as exc:  # a warm-up: the kernels compiled all the same
        print(f"warm_jit: identification on the warm-up runs: {exc}")
    print(f"warm_jit: model kernels compiled in {time.monotonic() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
