"""The control laws, behind one seam: a :class:`ControlLaw` and a registry of them by name.

The thesis's three (ch. 11), each a registered object:

- ``pid``      (11.5):  u = −k0·x0 − k1·x1 − k2·x2
- ``pid_sine`` (11.17): u = −k0·x0 − k1·x1 − k2·x2 − A·sin(2πft)
- ``pid_tv``   (11.18): u = −k0·x0 − k1·x1 − k2·x2 − kA·x0·sin(2πft)

with x1 = x − yr, x2 = ẋ − ẏr and x0 = ∫ x1 dt (11.4). Units: x0 [m s], x1 [m], x2 [m/s], u [V].
A law names the gains of :class:`Gains` it reads, checks them, gives ∂u/∂x0 (the controller's
anti-windup and bumpless transfer), its stability condition (Theorem 4 for the thesis's laws)
and the linear gains its sampled loop holds sample by sample (:mod:`.discrete`). The
controller's ``mode`` choices, ``experiment --mode``, ``gains --law`` and the demo take the
registry's names; a new law is one object and one :func:`register` call, in this module or
in a module named in ``PIEZO_STAGE_LAWS`` (comma-separated; imported at the first use of the
registry, so every process of a graph, which inherits the environment, knows the same laws).
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Protocol, TypeVar, overload, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GainError, SampledLoopError

if TYPE_CHECKING:
    from .bounds import Bounds, NominalPlant
    from .theorem4 import GainReport

Value = NDArray[np.float64] | float


@dataclass(frozen=True)
class Gains:
    """Gains of (11.5), (11.17), (11.18): k0 [V/(m s)], k1 [V/m], k2 [V s/m], kA [V/(m s)], A [V],
    f [Hz]; of the sliding-mode law (:mod:`.sliding`): ks [V], phi [m/s], delta [m/s]; of the
    adaptive law (:mod:`.adaptive`): tau_a [s], eps_a [m], kx_max [V/m].

    Thesis values (§11.4.1, §11.5.3): k1 = 5e6, k2 = 580, k0 = 1e9, kA = 1.5e9, f = 100 Hz;
    §11.5.2 uses A = 15 V with f = 10 Hz. ks and phi: the sliding-mode design on the thesis's
    bounds at 1 kHz (``piezo-stage gains --law smc``; no sensor noise given: delta = 0);
    tau_a, eps_a, kx_max: the adaptive law's design on the same (``--law adaptive``).
    """

    k0: float
    k1: float
    k2: float
    kA: float = 0.0
    A: float = 0.0
    f: float = 100.0
    ks: float = 0.0
    phi: float = 1.0
    delta: float = 0.0
    tau_a: float = 0.2528
    eps_a: float = 1e-8
    kx_max: float = 10.8e6

    def validate(self, mode: str = "pid") -> None:
        """Raise :class:`GainError` for non-finite or negative gains, or what law ``mode``
        refuses of them (:meth:`ControlLaw.check`).
        """
        law = law_named(mode)
        for key, value in asdict(self).items():
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise GainError(f"gain {key} must be a finite number, got {value!r}")
        for key in ("k0", "k1", "k2", "kA", "A", "ks", "delta", "kx_max"):
            if getattr(self, key) < 0:
                raise GainError(f"gain {key} must be >= 0, got {getattr(self, key)}")
        law.check(self)

    def to_dict(self) -> dict[str, float]:
        """The gains as a mapping."""
        return asdict(self)


#: §11.4.1 / §11.5.3 design.
THESIS_GAINS = Gains(k0=1e9, k1=5e6, k2=580.0, kA=1.5e9, A=15.0, f=100.0, ks=53.6, phi=0.32)


@dataclass(frozen=True)
class GainRow:
    """One gain of :class:`Gains` as a parameter: its name, what it is, unit and range."""

    name: str
    description: str
    unit: str
    range: tuple[float, float]
    #: where its default comes from
    origin: str = "the thesis's"

    @property
    def default(self) -> float:
        """Its value in :data:`THESIS_GAINS`."""
        return float(getattr(THESIS_GAINS, self.name))


_SMC_DESIGN = "the sliding-mode design on the thesis's bounds at 1 kHz"
_ADAPTIVE_DESIGN = "the adaptive law's design on the thesis's bounds"

#: every gain a law may read: the controller's gain parameters and the CLI's gain flags
GAIN_ROWS: tuple[GainRow, ...] = (
    GainRow("k0", "integral gain k0", "V/(m s)", (0.0, 1e15)),
    GainRow("k1", "proportional gain k1", "V/m", (0.0, 1e15)),
    GainRow("k2", "derivative gain k2", "V s/m", (0.0, 1e12)),
    GainRow("kA", "time-varying sine gain kA (pid_tv)", "V/(m s)", (0.0, 1e15)),
    GainRow("A", "sine amplitude A (pid_sine)", "V", (0.0, 1e4)),
    GainRow("f", "sine frequency f", "Hz", (1e-6, 1e6)),
    GainRow("ks", "switching gain ks (smc)", "V", (0.0, 1e4), _SMC_DESIGN),
    GainRow(
        "phi", "boundary layer phi of s = x2 + (k1/k2) x1 (smc)", "m/s", (1e-9, 1e6), _SMC_DESIGN
    ),
    GainRow(
        "delta",
        "dead band of s where smc does not switch (the sensor noise on s)",
        "m/s",
        (0.0, 1e6),
        _SMC_DESIGN,
    ),
    GainRow(
        "tau_a", "adaptation time constant tau_a (adaptive)", "s", (1e-6, 1e6), _ADAPTIVE_DESIGN
    ),
    GainRow(
        "eps_a",
        "smallest reference excursion the adaptive law learns from",
        "m",
        (1e-12, 1.0),
        _ADAPTIVE_DESIGN,
    ),
    GainRow(
        "kx_max",
        "largest stiffness estimate kappa_x_hat (adaptive)",
        "V/m",
        (0.0, 1e15),
        _ADAPTIVE_DESIGN,
    ),
)

#: the gains of the thesis's laws; the other rows are gains laws beyond them design themselves
THESIS_GAIN_NAMES = ("k0", "k1", "k2", "kA", "A", "f")
OWN_GAIN_ROWS = tuple(r for r in GAIN_ROWS if r.name not in THESIS_GAIN_NAMES)

#: (k0, k1, k2) of the linear loop at one sample
LinearGains = tuple[float, float, float]


@dataclass(frozen=True)
class LoopContext:
    """What a law's design rule may read beside the Assumption 2 bounds: the sampled loop's
    nominal ``plant`` and ``rate_hz`` (None: not known), its output delay, x2's filter
    time constant [s], the hysteresis's linearisation and the sensor's ``noise`` [m RMS].
    """

    plant: NominalPlant | None = None
    rate_hz: float | None = None
    delay_samples: int = 0
    derivative_tau: float = 0.0
    hysteresis: str = "disturbance"
    noise: float = 0.0


class ControlLaw(Protocol):
    """A law of the loop on the states of (11.4): u = ``split``'s two parts summed."""

    @property
    def name(self) -> str:
        """The ``mode`` that selects it."""
        ...

    @property
    def equation(self) -> str:
        """Its formula and source, one line (help texts and docs)."""
        ...

    @property
    def gains(self) -> tuple[str, ...]:
        """The fields of :class:`Gains` it reads."""
        ...

    def split(
        self, gains: Gains, t: ArrayLike, x0: ArrayLike, x1: ArrayLike, x2: ArrayLike
    ) -> tuple[Value, Value]:
        """(u_pid, u_excitation) at ``t`` [s] since the loop closed: its linear feedback and its
        added term (scalars stay floats, arrays broadcast).
        """
        ...

    def x0_coefficient(self, gains: Gains, t: float) -> float:
        """∂u/∂x0 at ``t`` [s] since the loop closed."""
        ...

    def check(self, gains: Gains) -> None:
        """Raise :class:`GainError` for gains this law cannot run with."""
        ...

    def theorem4(self, bounds: Bounds, gains: Gains) -> GainReport:
        """Its stability condition on the Assumption 2 ``bounds``."""
        ...

    def sampled_gains(self, gains: Gains, rate_hz: float, most: int) -> list[LinearGains]:
        """The linear gains its sampled loop holds at each sample of one period (one entry for
        a time-invariant law); :class:`SampledLoopError` where the loop is not linear
        periodic at ``rate_hz`` or its period holds more than ``most`` samples.
        """
        ...

    def design(
        self, bounds: Bounds, gains: Gains, margin: float, loop: LoopContext, given: set[str]
    ) -> dict[str, float]:
        """Its own gains (beyond k0, k1, k2) not in ``given``, from its design rule on
        ``bounds`` and ``loop`` with ``margin``; :class:`GainError` when ``loop`` lacks what the
        rule needs.
        """
        ...


class LawState(Protocol):
    """What a law learns while its loop runs (:class:`AdaptingLaw`), one per controller."""

    def configure(self, gains: Gains) -> None:
        """Take new gains, keeping what was learned."""
        ...

    def rebase(self, yr: float) -> None:
        """The loop closes at reference ``yr`` [m]."""
        ...

    def term(self, yr: float) -> float:
        """The term [V] it adds to the law's at reference ``yr``."""
        ...

    def adapt(self, x1: float, x2: float, yr: float, dt: float) -> None:
        """One update over ``dt`` [s] from the errors x1 [m], x2 [m/s] at reference ``yr``."""
        ...


@runtime_checkable
class AdaptingLaw(Protocol):
    """A law with a state of its own beside x0 (the adaptive law): the controller keeps one."""

    def estimate(self, gains: Gains) -> LawState:
        """A fresh state for a controller running the law with ``gains``."""
        ...


def law_state(law: ControlLaw, gains: Gains) -> LawState | None:
    """A fresh state of ``law`` when it learns, else None."""
    return law.estimate(gains) if isinstance(law, AdaptingLaw) else None


def _num(value: ArrayLike) -> Value:
    """``value`` as is when a float or an array (a controller's per-sample scalars stay Python
    floats: numpy costs microseconds per scalar operation), else as an array.
    """
    return value if isinstance(value, (float, np.ndarray)) else np.asarray(value)


def pid_term(gains: Gains, x0: ArrayLike, x1: ArrayLike, x2: ArrayLike) -> Value:
    """u_pid = −k0·x0 − k1·x1 − k2·x2, the PID of (11.5)."""
    return -gains.k0 * _num(x0) - gains.k1 * _num(x1) - gains.k2 * _num(x2)


def _sine(f: float, t: Value) -> Value:
    """sin(2πft), a float for a float."""
    return math.sin(2.0 * math.pi * f * t) if isinstance(t, float) else np.sin(2.0 * np.pi * f * t)


class Pid:
    """(11.5): u = −k0·x0 − k1·x1 − k2·x2, Theorem 4's law."""

    name = "pid"
    equation = "pid (11.5): u = -k0 x0 - k1 x1 - k2 x2"
    gains: tuple[str, ...] = ("k0", "k1", "k2")

    def split(
        self, gains: Gains, t: ArrayLike, x0: ArrayLike, x1: ArrayLike, x2: ArrayLike
    ) -> tuple[Value, Value]:
        """(−k0·x0 − k1·x1 − k2·x2, the law's added term)."""
        u_pid = pid_term(gains, x0, x1, x2)
        return u_pid, self._term(gains, _num(t), _num(x0))

    def _term(self, gains: Gains, t: Value, x0: Value) -> Value:
        """The term added to the PID (none here)."""
        if isinstance(t, float) and isinstance(x0, float):
            return 0.0
        return np.zeros(np.broadcast(t, x0).shape)[()]

    def x0_coefficient(self, gains: Gains, t: float) -> float:
        """−k0."""
        return -gains.k0

    def check(self, gains: Gains) -> None:
        """Nothing beyond :meth:`Gains.validate`."""
        return None

    def theorem4(self, bounds: Bounds, gains: Gains) -> GainReport:
        """Theorem 4 (11.6, 11.7) on k1, k2, k0; kA and f, where the law reads them, for sign."""
        from .theorem4 import validate_gains

        uses = self.gains
        return validate_gains(
            bounds,
            gains.k1,
            gains.k2,
            gains.k0,
            gains.kA if "kA" in uses else None,
            gains.f if "f" in uses else None,
        )

    def sampled_gains(self, gains: Gains, rate_hz: float, most: int) -> list[LinearGains]:
        """(k0, k1, k2) at every sample: the sine of (11.17) is an input, not a gain."""
        return [(gains.k0, gains.k1, gains.k2)]

    def design(
        self, bounds: Bounds, gains: Gains, margin: float, loop: LoopContext, given: set[str]
    ) -> dict[str, float]:
        """None beyond k0, k1, k2 (Theorem 4's, designed by the caller); kA, A and f are
        the user's.
        """
        return {}


class _Sine(Pid):
    """The sine laws' frequency check."""

    def check(self, gains: Gains) -> None:
        """The sine's frequency f > 0."""
        if gains.f <= 0:
            raise GainError(f"law {self.name!r} needs a frequency f > 0 Hz, got {gains.f}")


class PidSine(_Sine):
    """(11.17): the PID plus −A·sin(2πft); the sine is an input, not a gain of the loop."""

    name = "pid_sine"
    equation = "pid_sine (11.17): u = -k0 x0 - k1 x1 - k2 x2 - A sin(2 pi f t)"
    gains = ("k0", "k1", "k2", "A", "f")

    def _term(self, gains: Gains, t: Value, x0: Value) -> Value:
        return -gains.A * _sine(gains.f, t)


class PidTv(_Sine):
    """(11.18): the PID plus −kA·x0·sin(2πft), an integral gain that varies over 1/f."""

    name = "pid_tv"
    equation = "pid_tv (11.18): u = -(k0 + kA sin(2 pi f t)) x0 - k1 x1 - k2 x2"
    gains = ("k0", "k1", "k2", "kA", "f")

    def _term(self, gains: Gains, t: Value, x0: Value) -> Value:
        return -gains.kA * x0 * _sine(gains.f, t)

    def x0_coefficient(self, gains: Gains, t: float) -> float:
        """−(k0 + kA·sin(2πft))."""
        return -(gains.k0 + gains.kA * math.sin(2.0 * math.pi * gains.f * t))

    def sampled_gains(self, gains: Gains, rate_hz: float, most: int) -> list[LinearGains]:
        """k0 + kA·sin(2πf·kT) over the rate/f samples of one period (a Floquet check)."""
        if not gains.f > 0:
            raise SampledLoopError("law pid_tv needs f > 0")
        n_per = rate_hz / gains.f
        n_int = round(n_per) if math.isfinite(n_per) else 0
        if n_int < 1 or abs(n_per - n_int) > 1e-9 * n_per:
            raise SampledLoopError(
                "pid_tv check needs rate/f to be an integer (Floquet over one period), "
                f"got {n_per:.6g}"
            )
        if n_int > most:
            raise SampledLoopError(
                f"pid_tv check over rate/f = {n_int} samples needs more than the {most} a "
                "check may hold"
            )
        phase = 2.0 * math.pi * gains.f * (1.0 / rate_hz) * np.arange(n_int)
        return [(gains.k0 + gains.kA * math.sin(p), gains.k1, gains.k2) for p in phase]


_LAWS: dict[str, ControlLaw] = {}
L = TypeVar("L", bound=ControlLaw)
#: the environment variable naming modules that register more laws
LAW_MODULES = "PIEZO_STAGE_LAWS"
#: the package's laws in modules of their own (registered at the registry's first use)
BUILTIN_LAW_MODULES = ("piezo_stage.control.sliding", "piezo_stage.control.adaptive")
_modules_loaded = False


def _laws() -> dict[str, ControlLaw]:
    """The registry, after importing the package's law modules and those :data:`LAW_MODULES`
    names (once).
    """
    global _modules_loaded
    if not _modules_loaded:
        _modules_loaded = True
        for name in BUILTIN_LAW_MODULES:
            importlib.import_module(name)
        for name in filter(None, (m.strip() for m in os.environ.get(LAW_MODULES, "").split(","))):
            try:
                importlib.import_module(name)
            except Exception as exc:  # any failure of a user's module: said, with its name
                raise GainError(f"{LAW_MODULES}: module {name!r} does not load: {exc}") from None
    return _LAWS


def register(law: L) -> L:
    """Add ``law`` to the registry under its name (a name taken is refused)."""
    if law.name in _LAWS:
        raise ValueError(f"a control law named {law.name!r} is registered already")
    _LAWS[law.name] = law
    return law


def unregister(name: str) -> None:
    """Take law ``name`` out of the registry (a law a test registered)."""
    _LAWS.pop(name, None)


class LawNames(Sequence[str]):
    """The registered laws' names, read at each use: a parameter's or a flag's choices."""

    @overload
    def __getitem__(self, index: int) -> str: ...
    @overload
    def __getitem__(self, index: slice) -> Sequence[str]: ...
    def __getitem__(self, index: int | slice) -> str | Sequence[str]:
        return list(_laws())[index]

    def __len__(self) -> int:
        return len(_laws())

    def __iter__(self) -> Iterator[str]:
        return iter(list(_laws()))

    def __contains__(self, name: object) -> bool:
        return name in _laws()

    def __repr__(self) -> str:
        return f"LawNames({list(_laws())})"


#: the names of the registered laws (live)
LAW_NAMES = LawNames()


def law_named(mode: str) -> ControlLaw:
    """The registered law named ``mode``, else :class:`GainError` listing the names."""
    laws = _laws()
    law = laws.get(mode) if isinstance(mode, str) else None
    if law is None:
        raise GainError(f"unknown control law {mode!r}; expected one of {', '.join(laws)}")
    return law


def check_law(mode: str) -> str:
    """``mode`` when it names a registered law, else :class:`GainError` listing the names."""
    return law_named(mode).name


PID = register(Pid())
PID_SINE = register(PidSine())
PID_TV = register(PidTv())


def law_equations() -> str:
    """Every registered law's formula (help texts)."""
    return "; ".join(law.equation for law in _laws().values())


def excitation_term(mode: str, gains: Gains, t: ArrayLike, x0: ArrayLike) -> Value:
    """The term law ``mode`` adds to the PID: 0 (11.5), −A·sin(2πft) (11.17) or
    −kA·x0·sin(2πft) (11.18).
    """
    return law_named(mode).split(gains, t, x0, 0.0, 0.0)[1]


def x0_coefficient(mode: str, gains: Gains, t: float) -> float:
    """∂u/∂x0 at time t: −k0 for (11.5)/(11.17), −(k0 + kA·sin(2πft)) for (11.18)."""
    return law_named(mode).x0_coefficient(gains, t)


def control_law(
    mode: str, gains: Gains, t: ArrayLike, x0: ArrayLike, x1: ArrayLike, x2: ArrayLike
) -> Value:
    """Command u [V] of law ``mode``; t is the time since the loop was closed [s]."""
    u_pid, u_term = law_named(mode).split(gains, t, x0, x1, x2)
    return u_pid + u_term
