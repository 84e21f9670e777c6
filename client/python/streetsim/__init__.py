"""Python client for the streetsim gRPC simulator server (API streetsim.v1).

The generated stubs (streetsim/v1/*_pb2.py) are produced at build time into
<build>/python/streetsim; put both directories on PYTHONPATH:

    PYTHONPATH=client/python:build/python /usr/bin/python3 -c "import streetsim"
"""
# The package spans client/python/streetsim (this code) and <build>/python/streetsim (stubs).
__path__ = __import__("pkgutil").extend_path(__path__, __name__)

from streetsim.client import (  # noqa: E402,F401
    Client,
    Frame,
    Lidar,
    LidarOptions,
    Session,
    StreetsimError,
    pose_from_matrix,
    matrix_from_pose,
    remove_actor,
    move_actor,
    insert_actor,
)
from streetsim.replicas import ReplicaClient, replica_of  # noqa: E402,F401

__all__ = ["Client", "Frame", "Lidar", "LidarOptions", "ReplicaClient", "Session", "StreetsimError",
           "pose_from_matrix", "matrix_from_pose", "replica_of", "remove_actor", "move_actor",
           "insert_actor"]
