"""PNG figures of recorded experiments (matplotlib, Agg backend, imported lazily). No rclpy.

:func:`plot_bag` chooses the figures from what a bag holds: time series and hysteresis loops
(input voltage vs displacement, one colour per excitation run), the model against the data
when a ``bouc_wen_parameters`` message is present (10.15), and the closed-loop signals when
``controller_state`` is present (ch. 11, cf. the thesis's Figs. 11.5-11.8).
"""

from .bag_plots import BagTopics, PlotError, find_topics, plot_bag
from .figures import (
    closed_loop_figure,
    coupling_figure,
    hysteresis_figure,
    model_figure,
    scan_images_figure,
    scan_lines_figure,
    timeseries_figure,
    validation_figure,
)

__all__ = [
    "BagTopics",
    "PlotError",
    "closed_loop_figure",
    "coupling_figure",
    "find_topics",
    "hysteresis_figure",
    "model_figure",
    "plot_bag",
    "scan_images_figure",
    "scan_lines_figure",
    "timeseries_figure",
    "validation_figure",
]
