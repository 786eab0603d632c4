"""piezo_stage: identification and control of a piezoelectric positioning stage (ROS 2 Jazzy).

Implements Part II of Gomis i Bellmunt (2007): the normalized Bouc-Wen model, its analytic
limit-cycle identification and the time-varying PID. The core sub-packages (model,
identification, control, hardware, bag) are pure Python + numpy and never import rclpy.
"""

import os

# One BLAS thread unless the user says otherwise (set before numpy is first imported): on the
# small lab PC the nodes share two cores with the device threads, and OpenBLAS's spinning
# workers cost more than they give (``identify`` on the emulated rig's bag: 10 s with one
# thread, 15 s with two; 11 s and 27 s beside a busy core; bench/identification.py threads).
for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

from .errors import PiezoStageError  # noqa: E402

__version__ = "0.1.0"

__all__ = ["PiezoStageError"]
