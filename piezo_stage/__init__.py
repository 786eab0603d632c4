"""piezo_stage: identification and control of a piezoelectric positioning stage (ROS 2 Jazzy).

Implements Part II of Gomis i Bellmunt (2007): the normalized Bouc-Wen model, its analytic
limit-cycle identification and the time-varying PID. The core sub-packages (model,
identification, control, hardware, bag) are pure Python + numpy and never import rclpy.
"""

from .errors import PiezoStageError

__version__ = "0.1.0"

__all__ = ["PiezoStageError"]
