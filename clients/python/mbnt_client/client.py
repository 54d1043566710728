"""The client: :class:`Client` (uploads, jobs), :class:`Sequence` and :class:`Job`."""

import io
import json
import os
import time
from typing import Any, Dict, Iterable, List, Optional, Sequence as Seq, Union

import numpy as np
import requests
from tqdm.auto import tqdm

from . import _sse
from ._multipart import MultipartBody
from .errors import JobCancelled, JobFailed, WaitTimeout, error_from_response

Frame = Union[np.ndarray, str, "os.PathLike[str]"]

TERMINAL = ("succeeded", "failed", "cancelled")

# The server sends a keep-alive comment every 15 s; a stream silent for longer has stalled.
_EVENTS_READ_TIMEOUT = 45.0


class Client:
    """A connection to an ``mbnt serve`` service.

    Args:
        url: the service's base URL, e.g. ``http://127.0.0.1:8080``.
        token: the server's ``MBNT_API_TOKEN``; sent as ``Authorization: Bearer <token>``.
        timeout: seconds to wait for a connection and for each answer (uploads and label
            downloads included; waiting for a job is bounded by ``Job.wait(timeout=...)``).

    Every non-2xx answer raises an :class:`~mbnt_client.ApiError` subclass.
    """

    def __init__(self, url: str, token: Optional[str] = None, timeout: float = 60.0):
        self.url = url.rstrip("/")
        self.timeout = timeout
        self._session = requests.Session()
        if token is not None:
            self._session.headers["Authorization"] = f"Bearer {token}"

    def close(self) -> None:
        """Close the underlying HTTP connections."""
        self._session.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Client({self.url!r})"

    # -- HTTP ------------------------------------------------------------------------------

    def _request(self, method: str, path: str, **kwargs: Any) -> requests.Response:
        """Send a request to ``path`` (under the base URL); raise the typed error of a non-2xx answer."""
        kwargs.setdefault("timeout", self.timeout)
        response = self._session.request(method, self.url + path, **kwargs)
        if not 200 <= response.status_code < 300:
            try:
                raise error_from_response(response)
            finally:
                response.close()
        return response

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        return self._request(method, path, **kwargs).json()

    # -- operations ------------------------------------------------------------------------

    def health(self) -> Dict[str, Any]:
        """``GET /healthz``: ``{"status": "ok"}`` when the service and its storage answer."""
        return self._json("GET", "/healthz")

    def upload(
        self,
        frames: Iterable[Frame],
        timestamps: Optional[Seq[float]] = None,
        poses: Optional[Any] = None,
        name: Optional[str] = None,
    ) -> "Sequence":
        """Upload a sequence (``POST /v1/sequences``, multipart) and return it.

        Args:
            frames: at least 2 frames in time order, each an ``(N, 3)`` (or ``(N, C)``, C >= 3)
                numpy array of float32/float64, sent as ``.npy``, or the path of a PLY, PCD,
                KITTI ``.bin`` or ``.npy`` file, sent as it is (streamed from disk).
            timestamps: seconds, one per frame, strictly increasing (default: frame indices).
            poses: sensor-to-world transforms, a ``(T, 4, 4)`` array or a list of 4 x 4 matrices.
            name: a name for the sequence (at most 256 characters).
        """
        body = MultipartBody()
        meta: Dict[str, Any] = {}
        if name is not None:
            meta["name"] = name
        if timestamps is not None:
            meta["timestamps"] = [float(t) for t in np.asarray(timestamps, dtype=np.float64).ravel()]
        if poses is not None:
            p = np.asarray(poses, dtype=np.float64)
            if p.ndim != 3 or p.shape[1:] != (4, 4):
                raise ValueError(f"poses must be (T, 4, 4); got shape {p.shape}")
            meta["poses"] = p.reshape(len(p), 16).tolist()  # Matrix4: row-major, 16 numbers
        if meta:
            body.add("meta", json.dumps(meta).encode("utf-8"), "application/json")
        for k, frame in enumerate(frames):
            if isinstance(frame, (str, os.PathLike)):
                path = os.fspath(frame)
                body.add("frame", path, "application/octet-stream", os.path.basename(path))
            else:
                body.add("frame", _npy_bytes(frame, k), "application/octet-stream", f"{k:06d}.npy")
        view = self._json("POST", "/v1/sequences", data=body, headers={"Content-Type": body.content_type})
        return Sequence(self, view)

    def sequence(self, sequence_id: str) -> "Sequence":
        """The stored sequence ``sequence_id`` (``GET /v1/sequences/{id}``)."""
        return Sequence(self, self._json("GET", f"/v1/sequences/{sequence_id}"))

    def sequences(self, limit: int = 100) -> List["Sequence"]:
        """The stored sequences, newest first (``GET /v1/sequences``)."""
        answer = self._json("GET", "/v1/sequences", params={"limit": limit})
        return [Sequence(self, v) for v in answer["sequences"]]

    def fit(
        self, sequence_id: Union[str, "Sequence"], method: str = "mbnt", params: Optional[Dict[str, Any]] = None
    ) -> "Job":
        """Queue a fit (``POST /v1/jobs``) and return the queued job.

        Args:
            sequence_id: the sequence (its id or a :class:`Sequence`).
            method: ``mbnt``, ``ntp``, ``mbnsf`` or ``nsfp``.
            params: hyper-parameters (``FitParams`` of openapi.yaml, e.g. ``{"iterations": 200}``);
                an unknown or out-of-range one raises :class:`~mbnt_client.ValidationError` whose
                ``parameter`` is ``params.<name>``.
        """
        if isinstance(sequence_id, Sequence):
            sequence_id = sequence_id.id
        body: Dict[str, Any] = {"sequence_id": sequence_id, "method": method}
        if params is not None:
            body["params"] = params
        return Job(self, self._json("POST", "/v1/jobs", json=body))

    def job(self, job_id: str) -> "Job":
        """The job ``job_id`` (``GET /v1/jobs/{id}``)."""
        return Job(self, self._json("GET", f"/v1/jobs/{job_id}"))

    def jobs(
        self, status: Optional[str] = None, sequence_id: Optional[str] = None, limit: int = 100
    ) -> List["Job"]:
        """Jobs, newest first (``GET /v1/jobs``), optionally of one status and/or sequence."""
        params: Dict[str, Any] = {"limit": limit}
        if status is not None:
            params["status"] = status
        if sequence_id is not None:
            params["sequence_id"] = sequence_id
        return [Job(self, v) for v in self._json("GET", "/v1/jobs", params=params)["jobs"]]


def _npy_bytes(frame: Any, k: int) -> bytes:
    """Frame ``k`` as ``.npy`` bytes the server reads: 2-D, C >= 3 columns, little-endian float."""
    a = np.asarray(frame)
    if a.ndim != 2 or a.shape[1] < 3:
        raise ValueError(f"frame {k} must be an (N, 3) array; got shape {a.shape}")
    dtype = "<f8" if a.dtype == np.float64 else "<f4"
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a, dtype=dtype), allow_pickle=False)
    return buf.getvalue()


class _Resource:
    """A resource of the service (``_PREFIX/{id}``) and its latest JSON view."""

    _PREFIX = ""

    def __init__(self, client: Client, view: Dict[str, Any]):
        self._client = client
        self.view = view

    @property
    def id(self) -> str:
        """The resource's UUID."""
        return self.view["id"]

    def _path(self, tail: str = "") -> str:
        return f"{self._PREFIX}/{self.id}{tail}"

    def refresh(self):
        """Re-read the resource from the service."""
        self.view = self._client._json("GET", self._path())
        return self


class Sequence(_Resource):
    """An uploaded sequence. :attr:`view` is its JSON (``Sequence`` in openapi.yaml)."""

    _PREFIX = "/v1/sequences"

    @property
    def name(self) -> Optional[str]:
        """Its name, or ``None``."""
        return self.view.get("name")

    @property
    def frames(self) -> int:
        """Its number of frames."""
        return self.view["frames"]

    @property
    def points_per_frame(self) -> List[int]:
        """The number of points of each frame."""
        return self.view["points_per_frame"]

    @property
    def timestamps(self) -> List[float]:
        """The time axis: uploaded seconds, or frame indices (see :attr:`time_unit`)."""
        return self.view["timestamps"]

    @property
    def time_unit(self) -> str:
        """``"s"`` when timestamps were uploaded, ``"frame"`` otherwise."""
        return self.view["time_unit"]

    @property
    def has_poses(self) -> bool:
        """Whether poses were uploaded."""
        return self.view["has_poses"]

    def fit(self, method: str = "mbnt", params: Optional[Dict[str, Any]] = None) -> "Job":
        """Queue a fit of this sequence; see :meth:`Client.fit`."""
        return self._client.fit(self.id, method, params)

    def delete(self) -> None:
        """Delete the sequence, its finished jobs and their models (409 while a job runs)."""
        self._client._request("DELETE", self._path()).close()

    def __repr__(self) -> str:
        return f"Sequence(id={self.id!r}, frames={self.frames}, name={self.name!r})"


class Job(_Resource):
    """A fit job. :attr:`view` is its latest JSON (``Job`` in openapi.yaml)."""

    _PREFIX = "/v1/jobs"

    @property
    def sequence_id(self) -> str:
        """The UUID of the fitted sequence."""
        return self.view["sequence_id"]

    @property
    def status(self) -> str:
        """``queued``, ``running``, ``succeeded``, ``failed`` or ``cancelled`` (as last seen)."""
        return self.view["status"]

    @property
    def progress(self) -> Dict[str, Any]:
        """The last seen progress (``fraction``, ``iteration``, ``iterations``, ``loss``, ``eta_s``, ...)."""
        return self.view["progress"]

    @property
    def error(self) -> Optional[str]:
        """Why the job failed, or ``None``."""
        return self.view.get("error")

    def cancel(self) -> Dict[str, Any]:
        """Cancel the job and return its view after the request (409 once succeeded or failed)."""
        self.view = self._client._json("POST", self._path("/cancel"))
        return self.view

    def wait(self, progress: bool = True, timeout: Optional[float] = None, poll_interval: float = 1.0) -> Dict[str, Any]:
        """Wait until the job ends and return its final view.

        Follows the job's server-sent events (``GET /v1/jobs/{id}/events``); if the stream ends
        or breaks before the job does, polls ``GET /v1/jobs/{id}`` every ``poll_interval`` s.

        Args:
            progress: show a tqdm bar of the job's fraction done (on stderr).
            timeout: give up after this many seconds (:class:`~mbnt_client.WaitTimeout`).

        Raises:
            JobFailed: the job failed (``.error`` says why).
            JobCancelled: the job was cancelled.
            WaitTimeout: ``timeout`` passed first.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        bar = None
        if progress:
            bar = tqdm(
                total=100.0,
                desc=f"job {self.id[:8]}",
                bar_format="{desc}: {percentage:3.0f}%|{bar}| [{elapsed}{postfix}]",
            )

        def show(view: Dict[str, Any]) -> None:
            self.view = view
            if bar is None:
                return
            p = view.get("progress") or {}
            bar.n = 100.0 * float(p.get("fraction") or 0.0)
            post = {"status": view.get("status")}
            if p.get("iterations"):
                post["it"] = f"{p.get('iteration')}/{p.get('iterations')}"
            loss = p.get("loss")
            if loss:
                post["loss"] = f"{loss.get('total'):.4g}"
            if p.get("eta_s") is not None and view.get("status") == "running":
                post["eta"] = f"{p['eta_s']:.0f}s"
            bar.set_postfix(post, refresh=False)
            bar.refresh()

        def check_deadline() -> None:
            if deadline is not None and time.monotonic() > deadline:
                raise WaitTimeout(self.view, timeout)  # type: ignore[arg-type]

        try:
            ended = self._follow_events(show, deadline, check_deadline)
            while not ended:
                show(self._client._json("GET", self._path()))
                if self.status in TERMINAL:
                    break
                check_deadline()
                time.sleep(poll_interval if deadline is None else max(0.0, min(poll_interval, deadline - time.monotonic())))
        finally:
            if bar is not None:
                bar.close()
        if self.status == "failed":
            raise JobFailed(self.view)
        if self.status == "cancelled":
            raise JobCancelled(self.view)
        return self.view

    def _follow_events(self, show: Any, deadline: Optional[float], check_deadline: Any) -> bool:
        """Feed ``show`` every event of the job's stream; True once a terminal job was seen, False
        if the stream ended or broke before. An error answer (404, 401, ...) raises."""
        read_timeout = _EVENTS_READ_TIMEOUT
        if deadline is not None:
            read_timeout = max(0.1, min(read_timeout, deadline - time.monotonic()))
        try:
            response = self._client._request(
                "GET",
                self._path("/events"),
                stream=True,
                headers={"Accept": "text/event-stream"},
                timeout=(self._client.timeout, read_timeout),
            )
        except (requests.ConnectionError, requests.Timeout):
            return False
        with response:
            try:
                for event, data in _sse.events(response.iter_content(chunk_size=None)):
                    if event not in ("progress", "end"):
                        continue
                    show(json.loads(data))
                    if event == "end" or self.status in TERMINAL:
                        return True
                    check_deadline()
            except (requests.ConnectionError, requests.Timeout, requests.exceptions.ChunkedEncodingError, ValueError):
                return False
        return False

    def query(self, frame: int, indices: Optional[Seq[int]] = None, times: Optional[Seq[float]] = None) -> np.ndarray:
        """Where points of frame ``frame`` are at each of ``times``.

        Args:
            frame: the frame whose points are asked about (observed at that frame's time).
            indices: indices of the points in the frame (default: all its points).
            times: times on the sequence's time axis (seconds, or frame indices).

        Returns:
            float64 array ``(N, len(times), 3)``, each position in the sensor frame of its time.
        """
        if times is None:
            raise TypeError("query() needs times")
        body: Dict[str, Any] = {"frame": int(frame), "times": _floats(times)}
        if indices is not None:
            body["indices"] = [int(i) for i in np.asarray(indices).ravel()]
        return self._positions(body)

    def query_points(self, points: Any, t: float, times: Seq[float]) -> np.ndarray:
        """Where arbitrary ``points`` (an ``(N, 3)`` array) observed at time ``t`` are at each of ``times``.

        Returns:
            float64 array ``(N, len(times), 3)``.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must be (N, 3); got shape {p.shape}")
        return self._positions({"points": p.tolist(), "t": float(t), "times": _floats(times)})

    def _positions(self, body: Dict[str, Any]) -> np.ndarray:
        answer = self._client._json("POST", self._path("/query"), json=body)
        positions = answer["positions"]
        return np.asarray(positions, dtype=np.float64).reshape(len(positions), len(body["times"]), 3)

    def labels(self) -> Dict[str, np.ndarray]:
        """The scene-flow labels (``labels?format=npz``) as a dict of numpy arrays: ``flow_000``,
        ``flow_001``, ... (float32 ``(N_k, 3)``), ``object_000``, ... (int32 ``(N_k,)``, -1 for
        no moving body) and ``timestamps`` (float64 ``(T,)``)."""
        response = self._client._request("GET", self._path("/labels"), params={"format": "npz"})
        with np.load(io.BytesIO(response.content), allow_pickle=False) as archive:
            return {name: archive[name] for name in archive.files}

    def objects(self) -> List[Dict[str, Any]]:
        """The moving bodies of the scene model (the ``objects`` list of ``/v1/jobs/{id}/objects``):
        dicts with ``id``, ``frames_seen``, ``points_per_frame``, ``poses``, ``poses_sensor``
        (row-major 4 x 4 as 16 numbers) and ``extent``. Empty for models without bodies."""
        return self._client._json("GET", self._path("/objects"))["objects"]

    def poses(self) -> np.ndarray:
        """The sensor-to-world poses the fit worked with, a ``(T, 4, 4)`` float64 array (uploaded,
        or estimated by odometry). A fit without poses raises :class:`~mbnt_client.Conflict`."""
        poses = self._client._json("GET", self._path("/poses"))["poses"]
        return np.asarray(poses, dtype=np.float64).reshape(len(poses), 4, 4)

    def __repr__(self) -> str:
        return f"Job(id={self.id!r}, status={self.status!r})"


def _floats(values: Seq[float]) -> List[float]:
    return [float(v) for v in np.asarray(values, dtype=np.float64).ravel()]
