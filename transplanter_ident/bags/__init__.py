"""Bag I/O: the only subpackage that imports rosbags.

:mod:`.messages` decodes the accepted message types, :mod:`.reader` turns a bag into epochs,
:mod:`.writer` writes bags atomically, :mod:`.sim_bag` a simulated run (in real drivers' shapes
too), :mod:`.samples` provides the committed sample bags. Every failure is a :class:`BagError`.
"""

from transplanter_ident.bags.errors import BagError
from transplanter_ident.bags.messages import (
    ACCEPTED_TYPES,
    EXTRACTORS,
    FLOAT32,
    FLOAT64,
    IMU,
    INPUT_TYPES,
    JOINT_STATE,
    NS_PER_S,
    ODOMETRY,
    OUTPUT_FRAME_ID,
    OUTPUT_NAMESPACE,
    POSE_COV_STAMPED,
    QUATERNION_STAMPED,
    ROLES,
    TRUTH_STIFFNESS_TOPIC,
    TRUTH_VELOCITY_TOPIC,
    TWIST_COV_STAMPED,
    TWIST_STAMPED,
    TYPESTORE,
    VECTOR3_STAMPED,
    decode_message,
    normalize_msgtype,
    seconds,
    to_ns,
    yaw_quaternion,
)
from transplanter_ident.bags.reader import (
    BagData,
    Truth,
    open_reader,
    read_bag,
    read_epochs,
    read_samples,
    read_truth,
    summarize_rejections,
)
from transplanter_ident.bags.sim_bag import SimBagOptions, reading_parameters, write_sim_bag
from transplanter_ident.bags.writer import BagWriter, write_output_bag

__all__ = [
    "ACCEPTED_TYPES", "EXTRACTORS", "FLOAT32", "FLOAT64", "IMU", "INPUT_TYPES", "JOINT_STATE", "ODOMETRY", "POSE_COV_STAMPED",
    "QUATERNION_STAMPED", "TWIST_COV_STAMPED",
    "TWIST_STAMPED", "VECTOR3_STAMPED", "NS_PER_S", "OUTPUT_FRAME_ID", "OUTPUT_NAMESPACE", "ROLES",
    "TRUTH_STIFFNESS_TOPIC", "TRUTH_VELOCITY_TOPIC", "TYPESTORE", "BagData", "BagError", "BagWriter",
    "SimBagOptions", "Truth", "decode_message", "normalize_msgtype", "open_reader", "read_bag", "read_epochs",
    "read_samples", "read_truth", "reading_parameters", "seconds", "summarize_rejections", "to_ns", "write_output_bag",
    "write_sim_bag", "yaw_quaternion",
]
