"""The root of the exceptions piezo_stage raises.

Every exception class of the package derives from :class:`PiezoStageError`, through the base
class of the sub-package that raises it:

- model: :class:`~piezo_stage.model.errors.ModelError`
- identification: :class:`~piezo_stage.identification.errors.IdentificationError`
- control: :class:`~piezo_stage.control.errors.ControlError`
- hardware: :class:`~piezo_stage.hardware.errors.HardwareError`
- bag: :class:`~piezo_stage.bag.errors.BagError`
- launch: :class:`~piezo_stage.launch.errors.LaunchError`
- experiments: :class:`~piezo_stage.experiments.errors.ExperimentError`
- commissioning: :class:`~piezo_stage.commissioning.errors.CommissioningError`
- nodes: :class:`~piezo_stage.nodes.errors.NodeError`
- plotting: :class:`~piezo_stage.plotting.bag_plots.PlotError`

while the errors of the top-level modules derive from it directly
(``config_path.ConfigNotFoundError``, ``runtime_dir.RuntimeDirError``, the CLI's
``commands.identify.UsageError``). Many classes also derive from the standard exception that
describes them (``ValueError`` for bad input, ``FileNotFoundError`` for a missing file,
``KeyError`` for an unknown name, ``TimeoutError``), so code that catches those keeps catching
them.

``except PiezoStageError`` therefore catches whatever piezo_stage refuses or fails at (bad
input, unusable data, a device or graph failure), and not a programming error such as an
``AttributeError``. The warnings the package emits (``bag.BagDamageWarning``,
``bag.SkippedTopicWarning``) are ``UserWarning`` subclasses, outside this tree.
"""

from __future__ import annotations

__all__ = ["PiezoStageError"]


class PiezoStageError(Exception):
    """Base class of every exception raised by piezo_stage (see the module docstring)."""
