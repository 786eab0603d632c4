"""Helpers for the rig node tests: a probe node, diagnostics look-up, the emulator's command log."""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray

from piezo_stage.hardware.emulators import GCSDeviceModel


def sva_values(model: Any) -> list[float]:
    """Every voltage the amplifier emulator received (GCS ``SVA`` or MDT69x ``xvoltage=``)."""
    if isinstance(model, GCSDeviceModel):
        return [float(c.split()[2]) for c in list(model.commands) if c.startswith("SVA ")]
    return [float(c.split("=")[1]) for c in list(model.commands) if c.startswith("xvoltage=")]


class DiagnosticsProbe:
    """Keeps the latest /diagnostics status of one node (by fully qualified name)."""

    def __init__(self, node: Any, fqn: str) -> None:
        self.fqn = fqn
        self.latest: Any = None
        node.create_subscription(DiagnosticArray, "/diagnostics", self._on, 10)

    def _on(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            if s.name == self.fqn:
                self.latest = s

    @property
    def values(self) -> dict[str, str]:
        return {} if self.latest is None else {kv.key: kv.value for kv in self.latest.values}

    def value(self, key: str, default: str = "") -> str:
        return self.values.get(key, default)


def _serve_rig(conn: Any, kwargs: dict[str, Any]) -> None:
    """Child process of :class:`RigProcess`: the emulated ch. 11 rig and its orders."""
    from piezo_stage.hardware.emulators import Faults
    from piezo_stage.hardware.emulators.rig import RigEmulator
    from piezo_stage.hardware.optoncdt import frame_format
    from piezo_stage.model.parameter_set import shipped_parameter_set
    from piezo_stage.model.stage import SimulatedStage

    faults = Faults()
    rig = RigEmulator(
        SimulatedStage(shipped_parameter_set("ch11_rig")),
        frame_format(kwargs.pop("family")),
        kwargs.pop("measuring_range"),
        sensor_faults=faults,
        **kwargs,
    )
    rig.start()
    conn.send("started")
    try:
        while True:
            order, value = conn.recv()
            if order == "applied":
                conn.send(sva_values(rig.amplifier))
            elif order == "silent":
                faults.silent = bool(value)
                conn.send(None)
            elif order == "stop_sensor":
                rig.sensor_server.stop()
                conn.send(None)
            else:
                break
    finally:
        rig.stop()
        conn.send("stopped")


class RigProcess:
    """The emulated ch. 11 rig (:class:`RigEmulator`) in a process of its own, as hardware is:
    in the test's process its device threads share one GIL with the probe's callbacks and
    answered the driver late (a 0.5 s reply deadline missed, commands applied in bursts). The
    keyword arguments are RigEmulator's, with ``family`` and ``measuring_range`` for the
    sensor's frame format."""

    def __init__(self, **kwargs: Any) -> None:
        import multiprocessing

        self._kwargs = kwargs
        self._ctx = multiprocessing.get_context("spawn")  # no fork of a process running DDS
        self._conn: Any = None
        self._proc: Any = None
        self._applied: list[float] = []  # the command log as it was at stop()

    def _ask(self, order: str, value: Any = None, timeout: float = 30.0) -> Any:
        self._conn.send((order, value))
        if not self._conn.poll(timeout):
            raise TimeoutError(f"the emulated rig did not answer {order!r} in {timeout} s")
        return self._conn.recv()

    def start(self) -> "RigProcess":
        parent, child = self._ctx.Pipe()
        self._conn = parent
        self._proc = self._ctx.Process(target=_serve_rig, args=(child, dict(self._kwargs)))
        self._proc.start()
        if not parent.poll(60.0) or parent.recv() != "started":
            raise RuntimeError("the emulated rig did not start in 60 s")
        return self

    def stop(self) -> None:
        if self._proc is None:
            return
        try:
            if self._proc.is_alive():
                self._applied = self.applied()
                self._ask("stop", timeout=15.0)
        finally:
            self._proc.join(10.0)
            if self._proc.is_alive():
                self._proc.kill()
            self._proc = None

    def applied(self) -> list[float]:
        """Every voltage the amplifier received, in order (after :meth:`stop`: until then)."""
        if self._proc is None:
            return list(self._applied)
        return list(self._ask("applied"))

    def silence_sensor(self, silent: bool) -> None:
        self._ask("silent", silent)

    def stop_sensor(self) -> None:
        self._ask("stop_sensor")
