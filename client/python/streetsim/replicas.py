"""A client for several replicas of one streetsim deployment (docs/deploy.md).

Replicas share a state dir; each names the sessions and jobs it creates after itself
(``streetsim-1.s-4-0a1b2c3d``). Calls that carry no state (render, scenes, server info, creating a
session or a job) rotate over the replicas and fail over to the next one when a replica is
unreachable; a session's steps and a job's calls go to the replica its id names.
"""
import itertools
import threading
from typing import Dict, Iterator, List, Mapping, Optional, Sequence

import grpc

from streetsim.client import Client, Session, StreetsimError

# Codes after which a stateless call is tried on the next replica.
_FAIL_OVER = (grpc.StatusCode.UNAVAILABLE,)


def replica_of(object_id: str) -> str:
    """The replica an id names ("" for an id without one)."""
    return object_id.split(".", 1)[0] if "." in object_id else ""


class ReplicaClient:
    """``replicas``: replica name -> "host:port" (e.g. on loopback), or ``names`` with
    ``address_template`` such as ``"{replica}.streetsim-pods.default.svc:50051"`` (a StatefulSet's
    pods behind a headless Service). Other keyword arguments go to each replica's ``Client``."""

    def __init__(self, replicas: Optional[Mapping[str, str]] = None, names: Sequence[str] = (),
                 address_template: str = "", **client_options):
        if replicas is None:
            if not names or "{replica}" not in address_template:
                raise ValueError("ReplicaClient: give replicas={name: address}, or names and an "
                                 "address_template containing {replica}")
            replicas = {n: address_template.format(replica=n) for n in names}
        if not replicas:
            raise ValueError("ReplicaClient: no replicas")
        self._addresses: Dict[str, str] = dict(replicas)
        self._options = client_options
        self._clients: Dict[str, Client] = {}
        self._lock = threading.Lock()
        self._turn = itertools.cycle(sorted(self._addresses))

    @property
    def names(self) -> List[str]:
        return sorted(self._addresses)

    def client_for(self, replica: str) -> Client:
        with self._lock:
            if replica not in self._addresses:
                raise StreetsimError(grpc.StatusCode.NOT_FOUND, f"no replica named {replica!r} in this client")
            if replica not in self._clients:
                self._clients[replica] = Client(self._addresses[replica], **self._options)
            return self._clients[replica]

    def _any(self, call):
        """call(client) on the next replica in turn, then on the others while they are unreachable."""
        with self._lock:
            first = next(self._turn)
        order = self.names
        start = order.index(first)
        last_error = None
        for name in order[start:] + order[:start]:
            try:
                return call(self.client_for(name))
            except StreetsimError as e:
                if e.code not in _FAIL_OVER:
                    raise
                last_error = e
        raise last_error

    def _owner(self, object_id: str) -> Client:
        replica = replica_of(object_id)
        return self.client_for(replica) if replica else self.client_for(self.names[0])

    # -- stateless: any replica ---------------------------------------------------------------
    def server_info(self):
        return self._any(lambda c: c.server_info())

    def list_scenes(self):
        return self._any(lambda c: c.list_scenes())

    def render(self, *args, **kwargs):
        return self._any(lambda c: c.render(*args, **kwargs))

    def render_lidar(self, *args, **kwargs):
        return self._any(lambda c: c.render_lidar(*args, **kwargs))

    # -- sessions: created anywhere, then pinned to their replica --------------------------------
    def session(self, *args, **kwargs) -> Session:
        """A Session bound to the replica that created it (its id names it)."""
        return self._any(lambda c: c.session(*args, **kwargs))

    def session_client(self, session_id: str) -> Client:
        return self._owner(session_id)

    # -- jobs: created anywhere, then asked of their replica ---------------------------------------
    def train(self, *args, **kwargs):
        return self._any(lambda c: c.train(*args, **kwargs))

    def get_job(self, job_id: str):
        return self._owner(job_id).get_job(job_id)

    def cancel_job(self, job_id: str):
        return self._owner(job_id).cancel_job(job_id)

    def watch_job(self, job_id: str, timeout_s: float = 24 * 3600) -> Iterator:
        return self._owner(job_id).watch_job(job_id, timeout_s)

    def close(self):
        with self._lock:
            for c in self._clients.values():
                c.close()
            self._clients.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
