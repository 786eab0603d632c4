"""The Foxglove layout of a stage: what to look at while it runs (``piezo-stage view``) or in a
recorded bag, built with foxglove-sdk's typed layout model.

Four tabs, every message path on the stage's contract topics (docs/design.md §3) under
``namespace``:

- **Loop**: displacement, reference and the controller's reference against time; the voltage
  command and the applied voltage; the controller's error x1 and the terms of u
  (u_pid, u_ff, u_excitation, u); a loop-closed indicator.
- **Hysteresis**: the identifier's limit cycles as they are recorded (output against input,
  one XY curve per period, the loop forming), the composed rig loop's samples (displacement
  against applied voltage, each batch), the identified Bouc-Wen parameters (latched) and
  the excitation's state.
- **Scan**: a raster scan's image as it fills (``scan_view``'s ``scan_image``), the measured
  position (slow against fast axis) and each line's RMS error per axis.
- **Health**: /diagnostics (summary and detail: a node going red shows here first) and the
  nodes' log (/rosout).

``config/foxglove/piezo_stage.json`` is this layout for ``/piezo`` (test/test_live_layout.py
fails when it is stale); ``piezo-stage view --write-layout FILE --ns NS`` writes it for
another namespace.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from foxglove import layouts as fx

DEFAULT_NAMESPACE = "/piezo"


def _series(path: str, label: str, **extra: Any) -> fx.PlotSeries:
    return fx.PlotSeries(
        value=path, label=label, enabled=True, timestamp_method="receiveTime", **extra
    )


def _time_plot(title: str, series: list[fx.PlotSeries], y_label: str) -> fx.PlotPanel:
    return fx.PlotPanel(
        title=title,
        config=fx.PlotConfig(
            paths=series,
            show_legend=True,
            legend_display="top",
            y_axis_label=y_label,
            x_axis_val="timestamp",
            following_view_width=5.0,
            time_window_mode="sliding",
        ),
    )


def _xy_plot(title: str, y: str, x: str, label: str, x_label: str, y_label: str) -> fx.PlotPanel:
    """y against x within each message (the arrays of one message: one curve)."""
    return fx.PlotPanel(
        title=title,
        config=fx.PlotConfig(
            paths=[fx.PlotSeries(value=y, label=label, enabled=True)],
            x_axis_val="currentCustom",
            x_axis_path=fx.PlotXAxisPath(value=x, enabled=True),
            x_axis_label=x_label,
            y_axis_label=y_label,
            show_legend=True,
        ),
    )


def _column(*panels: Any) -> fx.SplitContainer:
    return fx.SplitContainer(direction="column", items=[fx.SplitItem(content=p) for p in panels])


def layout(namespace: str = DEFAULT_NAMESPACE) -> fx.Layout:
    """The stage's layout for the topics under ``namespace``."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""

    def t(topic: str) -> str:
        return f"{ns}/{topic}"

    loop = fx.SplitContainer(
        direction="row",
        items=[
            fx.SplitItem(
                proportion=3,
                content=_column(
                    _time_plot(
                        "position",
                        [
                            _series(f"{t('displacement')}.displacement", "x (sensor)"),
                            _series(f"{t('reference')}.displacement", "reference topic"),
                            _series(f"{t('controller_state')}.reference", "yr (controller)"),
                        ],
                        "m",
                    ),
                    _time_plot(
                        "voltage",
                        [
                            _series(f"{t('voltage_command')}.voltage", "command"),
                            _series(f"{t('voltage')}.voltage", "applied"),
                        ],
                        "V",
                    ),
                    _time_plot(
                        "controller",
                        [
                            _series(f"{t('controller_state')}.x1", "error x1 = x - yr"),
                        ],
                        "m",
                    ),
                    _time_plot(
                        "controller terms",
                        [
                            _series(f"{t('controller_state')}.u", "u"),
                            _series(f"{t('controller_state')}.u_pid", "u_pid"),
                            _series(f"{t('controller_state')}.u_ff", "u_ff"),
                            _series(f"{t('controller_state')}.u_excitation", "u_excitation"),
                        ],
                        "V",
                    ),
                ),
            ),
            fx.SplitItem(
                proportion=1,
                content=_column(
                    fx.IndicatorPanel(
                        title="loop",
                        config=fx.IndicatorConfig(
                            path=f"{t('controller_state')}.loop_closed",
                            style="background",
                            fallback_color="#a0a0a0",
                            fallback_label="no controller",
                            rules=[
                                fx.IndicatorRule(
                                    raw_value="true", operator="=", color="#2e7d32", label="closed"
                                ),
                                fx.IndicatorRule(
                                    raw_value="false", operator="=", color="#c62828", label="open"
                                ),
                            ],
                        ),
                    ),
                    fx.IndicatorPanel(
                        title="saturated",
                        config=fx.IndicatorConfig(
                            path=f"{t('controller_state')}.saturated",
                            style="bulb",
                            rules=[
                                fx.IndicatorRule(
                                    raw_value="true",
                                    operator="=",
                                    color="#ef6c00",
                                    label="at a voltage limit",
                                )
                            ],
                            fallback_color="#2e7d32",
                            fallback_label="within limits",
                        ),
                    ),
                    fx.RawMessagesPanel(
                        title="controller state",
                        config=fx.RawMessagesConfig(topic_path=t("controller_state")),
                    ),
                ),
            ),
        ],
    )
    hysteresis = fx.SplitContainer(
        direction="row",
        items=[
            fx.SplitItem(
                proportion=2,
                content=_column(
                    _xy_plot(
                        "limit cycle (identification)",
                        f"{t('limit_cycles')}.output[:]",
                        f"{t('limit_cycles')}.input[:]",
                        "output",
                        "input",
                        "output",
                    ),
                    _xy_plot(
                        "rig loop: displacement vs applied voltage",
                        f"{t('loop_samples')}.displacement[:]",
                        f"{t('loop_samples')}.applied[:]",
                        "x",
                        "V",
                        "m",
                    ),
                ),
            ),
            fx.SplitItem(
                proportion=1,
                content=_column(
                    fx.RawMessagesPanel(
                        title="identified Bouc-Wen parameters",
                        config=fx.RawMessagesConfig(topic_path=t("bouc_wen_parameters")),
                    ),
                    fx.RawMessagesPanel(
                        title="excitation", config=fx.RawMessagesConfig(topic_path=t("excitation"))
                    ),
                ),
            ),
        ],
    )
    health = fx.SplitContainer(
        direction="row",
        items=[
            fx.SplitItem(
                content=_column(
                    fx.DiagnosticsSummaryPanel(
                        title="diagnostics",
                        config=fx.DiagnosticsSummaryConfig(
                            topic_to_render="/diagnostics", sort_by_level=True
                        ),
                    ),
                    fx.DiagnosticsDetailPanel(title="diagnostics detail"),
                )
            ),
            fx.SplitItem(content=fx.LogPanel(title="log (/rosout)")),
        ],
    )
    return fx.Layout(
        content=fx.TabContainer(
            tabs=[
                fx.TabItem(title="Loop", content=loop),
                fx.TabItem(title="Hysteresis", content=hysteresis),
                fx.TabItem(title="Scan", content=_scan_tab(t)),
                fx.TabItem(title="Health", content=health),
            ]
        )
    )


def _scan_tab(t: Any) -> fx.SplitContainer:
    """A raster scan (``scan_view``'s topics): the image as it fills, the stage's path, and
    each line's error as it is scanned."""
    image = fx.ImagePanel(
        title="scan image",
        config=fx.ImageConfig(image_mode=fx.ImageModeConfig(image_topic=t("scan_image"))),
    )
    path = fx.PlotPanel(
        title="measured position: slow against fast axis",
        config=fx.PlotConfig(
            paths=[fx.PlotSeries(value=f"{t('scan_position')}.point.y", label="y", enabled=True)],
            x_axis_val="custom",
            x_axis_path=fx.PlotXAxisPath(value=f"{t('scan_position')}.point.x", enabled=True),
            x_axis_label="fast axis [m]",
            y_axis_label="slow axis [m]",
        ),
    )
    lines = _time_plot(
        "each line's RMS error",
        [
            _series(f"{t('scan_line_rms')}.point.x", "fast axis"),
            _series(f"{t('scan_line_rms')}.point.y", "slow axis"),
        ],
        "m",
    )
    return fx.SplitContainer(
        direction="row",
        items=[
            fx.SplitItem(proportion=2, content=image),
            fx.SplitItem(proportion=1, content=_column(path, lines)),
        ],
    )


def layout_json(namespace: str = DEFAULT_NAMESPACE) -> str:
    """The layout as the JSON the Foxglove app imports (Layouts > Import from file)."""
    return json.dumps(json.loads(layout(namespace).to_json()), indent=1, sort_keys=True) + "\n"


def write_layout(path: str | Path, namespace: str = DEFAULT_NAMESPACE) -> Path:
    path = Path(path)
    path.write_text(layout_json(namespace), encoding="utf-8")
    return path


def message_paths(data: Any) -> list[str]:
    """Every message path in a layout's JSON (plot series and x axes, indicators, raw
    messages, diagnostics and image topics)."""
    found: list[str] = []
    if isinstance(data, dict):
        for key, value in data.items():
            if (
                key in ("value", "path", "topicPath", "topicToRender", "imageTopic")
                and isinstance(value, str)
                and value.startswith("/")
            ):
                found.append(value)
            else:
                found += message_paths(value)
    elif isinstance(data, list):
        for item in data:
            found += message_paths(item)
    return found
