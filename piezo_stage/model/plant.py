"""The simulated plants (no ROS here); the amplifier/sensor chain is in :mod:`.stage`.

- :class:`StaticPlant`: the static model of ch. 10, y = sum kappa_i v^i + kappa_w w + y0 (10.15),
  w driven by input_sign * v.
- :class:`DynamicPlant`: the dynamic model of ch. 11, m x'' + c x' + Phi(x) = u (11.1)-(11.3)
  with Phi = sum kappa_i x^i + kappa_w w (10.4), u held over each step (zero-order hold);
  output x + y0. Integrated by exponential Lobatto collocation (see ``_plant_kernels``):
  the stiff ~7 kHz mode of the thesis rig is propagated exactly, the hysteresis exactly along
  the x path, sub-steps chosen by an error estimate.
- :class:`~.stage.AmplifierModel`, :class:`~.stage.SensorModel`,
  :class:`~.stage.SimulatedStage` (in :mod:`.stage`, which builds on this module; all of them
  importable from :mod:`piezo_stage.model`):
  ``step(command_voltage, dt) -> (applied, displacement, status)``.
- :func:`simulate_reference`: scipy ``solve_ivp`` with velocity-reversal events, the slow
  converged baseline used by the tests and ``bench/plant.py``.
"""

from __future__ import annotations

import math
from typing import Literal, TypeAlias, cast

import numpy as np
from numpy.polynomial import legendre
from numpy.typing import NDArray

from . import _branches
from . import _plant_kernels as K
from .bouc_wen import BoucWenParameters, check_w0, polynomial
from .errors import InputSignalError, InvalidCommandError, ParameterValueError
from .parameter_set import Dynamics

Array: TypeAlias = NDArray[np.float64]

__all__ = [
    "StaticPlant",
    "DynamicPlant",
    "simulate_reference",
    "length_scale",
    "lobatto_nodes",
]


#: default local tolerance of DynamicPlant: <= 1e-6 relative error on the bench inputs
#: (bench/plant.py)
DEFAULT_TOL = 3e-8


def _check_dt(dt: float) -> float:
    dt = float(dt)
    if not (math.isfinite(dt) and dt > 0.0):
        raise InputSignalError(f"time step dt must be finite and > 0, got {dt!r}")
    return dt


def _check_value(value: float, name: str) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise InvalidCommandError(f"{name} must be finite, got {value!r}")
    return value


# --------------------------------------------------------------------------------------- plants
class StaticPlant:
    """Static model (10.15): step(v) -> y; the hysteretic state w is kept between calls."""

    def __init__(self, params: BoucWenParameters, w0: float = 0.0, v0: float = 0.0) -> None:
        params.validate()
        self.params = params
        self._tab = _branches.tables(params.sigma, params.n)
        self._v1, self._w1 = np.zeros(1), np.zeros(1)  # step() buffers
        self.reset(w0, v0)

    def reset(self, w0: float = 0.0, v0: float = 0.0) -> None:
        """Restart at input v0 with hysteretic state w0."""
        w0 = check_w0(w0)
        v0 = _check_value(v0, "v0")
        self._walker = np.array([0.0, 0.0, 0.0, self.params.input_sign * v0, w0])
        self._v = v0

    @property
    def w(self) -> float:
        """Current hysteretic state w."""
        return float(self._walker[4])

    def output(self) -> float:
        """Current output y for the last input."""
        p = self.params
        total = 0.0
        for k in reversed(p.kappa):  # sum kappa_i v^i (Horner)
            total = (total + k) * self._v
        return total + p.kappa_w * float(self._walker[4]) + p.y0

    def step(self, v: float) -> float:
        """Apply input v (the path from the previous input is monotone) and return y (10.15)."""
        self._v1[0] = self.params.input_sign * _check_value(v, "input v")
        K.static_walk(self._tab, self.params.rho, self._walker, self._v1, self._w1)
        self._v = self._v1[0] * self.params.input_sign
        return self.output()

    def simulate(self, v: Array) -> Array:
        """Outputs for a sequence of inputs, continuing from the current state."""
        v = np.ascontiguousarray(v, dtype=float)
        if v.ndim != 1 or not np.all(np.isfinite(v)):
            raise InputSignalError("inputs must be a 1-D array of finite samples")
        w = np.empty_like(v)
        K.static_walk(self._tab, self.params.rho, self._walker, self.params.input_sign * v, w)
        if v.size:
            self._v = float(v[-1])
        p = self.params
        return polynomial(p.kappa, v) + p.kappa_w * w + p.y0


def lobatto_nodes(count: int) -> Array:
    """Gauss-Lobatto nodes on [0, 1]: 0, the roots of P'_{count-1} mapped to (0, 1), 1."""
    interior = legendre.Legendre.basis(count - 1).deriv().roots() if count > 2 else np.array([])
    return np.concatenate([[0.0], (np.sort(np.real(interior)) + 1.0) / 2.0, [1.0]])


def _lagrange_weights(nodes: Array, points: Array) -> Array:
    """W[p, j] = l_j(points[p]) for the Lagrange basis on ``nodes``."""
    out = np.ones((points.size, nodes.size))
    for j, xj in enumerate(nodes):
        for k, xk in enumerate(nodes):
            if k != j:
                out[:, j] *= (points - xk) / (xj - xk)
    return out


class DynamicPlant:
    """m x'' + c x' + sum kappa_i x^i + kappa_w w = u (11.1)-(11.3), ZOH input, output x + y0.

    ``tol`` is the local error allowed per piece relative to :func:`length_scale`
    (max(1/rho, kappa_w/kappa_x): the displacement over which w changes by O(1), or the one
    the hysteretic force can cause); ``nodes`` the Lobatto collocation nodes per piece.
    Any step dt can be used (nothing is precomputed per dt).
    """

    def __init__(
        self,
        params: BoucWenParameters,
        dynamics: Dynamics,
        x0: float = 0.0,
        xdot0: float = 0.0,
        w0: float = 0.0,
        tol: float = DEFAULT_TOL,
        nodes: int = 4,
    ) -> None:
        params.validate()
        if not isinstance(dynamics, Dynamics):
            raise ParameterValueError("dynamics must be a Dynamics(m, c)")
        if not params.kappa_x > 0.0:
            raise ParameterValueError(
                f"the dynamic plant needs kappa_x > 0 (11.2), got {params.kappa_x!r}"
            )
        if not (1e-14 <= tol <= 1e-2):
            raise ParameterValueError(f"tol must be in [1e-14, 1e-2], got {tol!r}")
        if nodes not in (4, 5):  # 3 nodes showed a systematic drift in long ZOH-ringing runs
            raise ParameterValueError(f"nodes must be 4 or 5, got {nodes!r}")
        self.params = params
        self.dynamics = dynamics
        self.tol = float(tol)
        self._tab = _branches.tables(params.sigma, params.n)
        self._model = (
            params.rho,
            params.kappa_w,
            params.kappa_x,
            0.0,
            dynamics.m,
            dynamics.c,
            float(params.input_sign),
        )
        self._kpoly = np.array(params.kappa[1:], dtype=float)
        self._nodes = lobatto_nodes(nodes)
        self._checks = np.array([0.5 * (self._nodes[-2] + self._nodes[-1])])  # defect check point
        # (numpy's stubs type the inverse of any float matrix as floating[Any]: this one is float64)
        self._vinv = cast(Array, np.linalg.inv(np.vander(self._nodes, nodes, increasing=True)))
        self._lagrange = _lagrange_weights(self._nodes, self._checks)
        self.stats = np.zeros(K.STATS_SIZE)
        self._tol_x = self.tol * length_scale(params)
        self._u1, self._x1, self._v1, self._w1 = (np.zeros(1) for _ in range(4))  # step() buffers
        self._work = K.workspace(self._nodes, self._checks)
        self.reset(x0, xdot0, w0)

    # ------------------------------------------------------------------ state
    def reset(self, x0: float = 0.0, xdot0: float = 0.0, w0: float = 0.0) -> None:
        """Restart from x(0) = x0, x'(0) = xdot0, w(0) = w0."""
        x0 = _check_value(x0, "x0")
        xdot0 = _check_value(xdot0, "xdot0")
        w0 = check_w0(w0)
        self._state = np.zeros(K.STATE_SIZE)
        self._state[K.X] = x0
        self._state[K.V] = xdot0
        self._state[K.XC] = self.params.input_sign * x0
        self._state[K.WC] = w0
        self._state[K.HPREF] = math.inf

    @property
    def x(self) -> float:
        """Position x [m] (11.1) (the output adds y0)."""
        return float(self._state[K.X])

    @property
    def xdot(self) -> float:
        """Velocity x' [m/s]."""
        return float(self._state[K.V])

    @property
    def w(self) -> float:
        """Hysteretic state w."""
        return float(self._state[K.WC])

    def output(self) -> float:
        """Displacement x + y0."""
        return self.x + self.params.y0

    # ------------------------------------------------------------------ integration
    def _run(self, u: Array, dt: float, x: Array, v: Array, w: Array) -> None:
        K.integrate(
            self._tab,
            self._model,
            self._kpoly,
            self._nodes,
            self._checks,
            self._vinv,
            self._lagrange,
            dt,
            self._tol_x,
            1e-7 * dt,
            self._state,
            u,
            x,
            v,
            w,
            self.stats,
            self._work,
        )

    def simulate(self, u: Array, dt: float) -> tuple[Array, Array, Array]:
        """States (x, x', w) at the end of each step k, u[k] held over [k dt, (k+1) dt]."""
        dt = _check_dt(dt)
        u = np.ascontiguousarray(u, dtype=float)
        if u.ndim != 1 or not np.all(np.isfinite(u)):
            raise InputSignalError("u must be a 1-D array of finite samples")
        x = np.empty_like(u)
        v = np.empty_like(u)
        w = np.empty_like(u)
        self._run(u, dt, x, v, w)
        return x, v, w

    def step(self, u: float, dt: float) -> float:
        """Hold u over dt and return the displacement x + y0 at the end (cheap per call)."""
        self._u1[0] = _check_value(u, "input u")
        self._run(self._u1, _check_dt(dt), self._x1, self._v1, self._w1)
        return float(self._x1[0]) + self.params.y0


def length_scale(params: BoucWenParameters) -> float:
    """max(1/rho, kappa_w/kappa_x) [m]: the displacement scale of the hysteresis (tolerances)."""
    return max(1.0 / params.rho, params.kappa_w / abs(params.kappa_x))


#: the solve_ivp methods :func:`simulate_reference` can use
IvpMethod: TypeAlias = Literal["RK23", "RK45", "DOP853", "Radau", "BDF", "LSODA"]


class _Reversal:
    """A terminal solve_ivp event of :func:`simulate_reference`: x' = 0, crossed in
    ``direction`` (-1: downwards, a maximum of x; 1: upwards, a minimum of x).
    """

    terminal = True

    def __init__(self, direction: float) -> None:
        self.direction = direction

    def __call__(self, _t: float, z: Array, _uk: float) -> float:
        return float(z[1])


def simulate_reference(
    params: BoucWenParameters,
    dynamics: Dynamics,
    u: Array,
    dt: float,
    x0: float = 0.0,
    xdot0: float = 0.0,
    w0: float = 0.0,
    method: IvpMethod = "DOP853",
    rtol: float = 1e-12,
    reversal_events: bool = True,
) -> tuple[Array, Array, Array]:
    """Baseline: scipy ``solve_ivp`` on (x, x', w) of (11.1)-(11.3), one call per ZOH interval.

    With ``reversal_events`` (the converged reference) every interval is restarted at each
    velocity reversal x' = 0, where the |x'| of (9.2) has a kink, so tight tolerances converge;
    without, the solver steps over the kinks as a plain ``solve_ivp`` user would. Slow: the
    reference for tests and bench/plant.py. atol is rtol times the displacement scale
    min(length_scale, max|u| / kappa_x) (and that times omega for x', 1 for w).
    """
    from scipy.integrate import solve_ivp  # lazy: the baseline only, not the nodes' import

    params.validate()
    dt = _check_dt(dt)
    m, c = dynamics.m, dynamics.c
    rho, sigma, n, kw, sgn = params.rho, params.sigma, params.n, params.kappa_w, params.input_sign
    kappa = np.array(params.kappa)
    powers = np.arange(1, kappa.size + 1)
    omega = math.sqrt((params.kappa_x + kw * rho) / m)
    u = np.asarray(u, dtype=float)
    u_peak = float(np.max(np.abs(u))) if u.size else 0.0
    scale = (
        min(length_scale(params), u_peak / abs(params.kappa_x))
        if u_peak > 0.0
        else length_scale(params)
    )
    atol = rtol * np.array([scale, scale * omega, 1.0])

    def rhs(_t: float, z: Array, uk: float) -> list[float]:
        x, v, w = z
        a = abs(w)
        vin = sgn * v
        wdot = rho * (vin - sigma * abs(vin) * a ** (n - 1.0) * w + (sigma - 1.0) * vin * a**n)
        return [v, (uk - c * v - float(np.dot(kappa, x**powers)) - kw * w) / m, wdot]

    falling = _Reversal(-1.0)  # x' crosses zero downwards: a maximum of x
    rising = _Reversal(1.0)  # x' crosses zero upwards: a minimum of x
    state = np.array([x0, xdot0, check_w0(w0)], dtype=float)
    out = np.empty((3, len(u)))
    after_event: _Reversal | None = None  # the event just handled: the next one is the other
    for k, uk in enumerate(u):
        t, end = 0.0, dt
        while t < end:
            events: _Reversal | None = None
            if reversal_events:
                if after_event is not None:
                    events = rising if after_event is falling else falling
                else:
                    moving = (
                        state[1] if state[1] != 0.0 else rhs(t, state, uk)[1]
                    )  # at rest: where it goes
                    events = falling if moving > 0.0 else (rising if moving < 0.0 else None)
            sol = solve_ivp(
                rhs,
                (t, end),
                state,
                method=method,
                rtol=rtol,
                atol=atol,
                events=events,  # type: ignore[arg-type]  # stubs: events(t, y), but scipy adds args
                args=(uk,),
            )
            state = sol.y[:, -1].copy()
            if sol.status == 1 and sol.t[-1] < end:
                t = sol.t[-1]
                after_event = events
            else:
                t = end
                # once the velocity has the sign of the new direction, it picks the next event
                if (
                    after_event is not None
                    and (state[1] < 0.0) == (after_event is falling)
                    and state[1] != 0.0
                ):
                    after_event = None
        state[2] = min(1.0, max(-1.0, state[2]))
        out[:, k] = state
    return out[0], out[1], out[2]
