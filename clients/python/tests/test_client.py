"""The client against a real `mbnt serve` (see conftest.py; skipped without MBNT_BIN)."""

import subprocess
import sys
import time

import numpy as np
import pytest

import mbnt_client
from mbnt_client import (
    Client,
    Conflict,
    JobCancelled,
    LimitExceeded,
    NotFound,
    PayloadTooLarge,
    Unauthorized,
    ValidationError,
    WaitTimeout,
)
from mbnt_client import client as client_module

from conftest import MBNT_BIN, running_server

pytestmark = pytest.mark.skipif(
    not MBNT_BIN, reason="MBNT_BIN is not set: it must name an mbnt binary (e.g. target/release/mbnt)"
)

TIMESTAMPS = [0.0, 0.1, 0.2]
TINY = {"iterations": 3, "hidden_width": 16, "hidden_layers": 2, "seed": 1}
UNKNOWN_JOB = "00000000-0000-4000-8000-000000000000"


def _yaw_pose(yaw, t):
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = t
    return pose


def synthetic_scene():
    """Three frames in sensor coordinates of a sensor driving along x: a ground patch and a wall
    (static in the world) and a box moving 1 m per frame (10 m/s); returns (frames, poses)."""
    rng = np.random.default_rng(7)
    gx, gy = np.meshgrid(np.arange(-9.0, 9.1, 1.2), np.arange(-9.0, 9.1, 1.2))
    ground = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -1.7)], axis=1)
    wx, wz = np.meshgrid(np.arange(-8.0, 8.1, 0.5), np.arange(-1.5, 1.6, 0.5))
    wall = np.stack([wx.ravel(), np.full(wx.size, 8.0), wz.ravel()], axis=1)
    # Box surface: 4.0 x 1.8 x 1.5 m, corner at (2, -4, -1.6).
    u = rng.uniform(0.0, 1.0, size=(160, 3))
    face = rng.integers(0, 6, size=160)
    box = u * [4.0, 1.8, 1.5]
    axis = face % 3
    box[np.arange(160), axis] = np.where(face < 3, 0.0, 1.0) * np.array([4.0, 1.8, 1.5])[axis]
    box += [2.0, -4.0, -1.6]
    frames, poses = [], []
    for k in range(3):
        world = np.concatenate([ground, wall, box + [1.0 * k, 0.0, 0.0]])
        pose = _yaw_pose(0.02 * k, [0.3 * k, 0.0, 0.0])  # sensor-to-world
        sensor = (world - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - t), row-wise
        frames.append(sensor.astype(np.float32))
        poses.append(pose)
    return frames, np.stack(poses)


@pytest.fixture(scope="module")
def client(server_url):
    with Client(server_url, timeout=30) as c:
        yield c


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene()


@pytest.fixture(scope="module")
def sequence(client, scene):
    frames, poses = scene
    return client.upload(frames, timestamps=TIMESTAMPS, poses=poses, name="synthetic")


@pytest.fixture(scope="module")
def fitted(client, sequence):
    job = client.fit(sequence.id, method="mbnt", params=TINY)
    final = job.wait(progress=False, timeout=60)
    assert final["status"] == "succeeded"
    return job


def test_upload_numpy_frames(client, sequence, scene):
    frames, _ = scene
    assert sequence.frames == 3
    assert sequence.points_per_frame == [len(f) for f in frames]
    assert sequence.timestamps == TIMESTAMPS
    assert sequence.time_unit == "s"
    assert sequence.has_poses
    assert sequence.name == "synthetic"
    again = client.sequence(sequence.id)
    assert again.view == sequence.view
    assert sequence.id in [s.id for s in client.sequences()]


def test_fit_wait_succeeds(client, fitted, sequence):
    assert fitted.status == "succeeded"
    assert fitted.sequence_id == sequence.id
    assert fitted.progress["fraction"] == 1.0
    assert fitted.view["params"]["iterations"] == 3
    assert fitted.view["params"]["hidden_width"] == 16
    again = client.job(fitted.id)
    assert again.status == "succeeded"
    assert fitted.id in [j.id for j in client.jobs(status="succeeded", sequence_id=sequence.id)]


def test_query_frame_at_its_time_gives_the_input_points(fitted, scene):
    frames, _ = scene
    for k, frame in enumerate(frames):
        positions = fitted.query(k, times=TIMESTAMPS)
        assert positions.shape == (len(frame), 3, 3)
        assert np.isfinite(positions).all()
        np.testing.assert_allclose(positions[:, k, :], frame, atol=1e-4)
    some = fitted.query(1, indices=[0, 5, 7], times=[0.0, 0.2])
    assert some.shape == (3, 2, 3)
    np.testing.assert_allclose(some, fitted.query(1, times=[0.0, 0.2])[[0, 5, 7]], atol=1e-6)


def test_query_points(fitted, scene):
    frames, _ = scene
    points = frames[0][:10]
    positions = fitted.query_points(points, t=0.0, times=[0.0, 0.1, 0.2, 0.05])
    assert positions.shape == (10, 4, 3)
    assert np.isfinite(positions).all()
    np.testing.assert_allclose(positions[:, 0, :], points, atol=1e-4)


def test_labels(fitted, scene):
    frames, _ = scene
    labels = fitted.labels()
    np.testing.assert_array_equal(labels["timestamps"], TIMESTAMPS)
    assert labels["timestamps"].dtype == np.float64
    flows = sorted(k for k in labels if k.startswith("flow_"))
    objects = sorted(k for k in labels if k.startswith("object_"))
    assert flows and flows == [f"flow_{k:03d}" for k in range(len(flows))]
    assert objects == [f"object_{k:03d}" for k in range(len(objects))]
    assert len(objects) == len(frames)
    for k, name in enumerate(flows):
        assert labels[name].shape == (len(frames[k]), 3)
        assert labels[name].dtype == np.float32
    for k, name in enumerate(objects):
        assert labels[name].shape == (len(frames[k]),)
        assert labels[name].dtype == np.int32
        assert (labels[name] >= -1).all()


def test_objects_and_poses(fitted, scene):
    _, poses = scene
    objects = fitted.objects()
    assert isinstance(objects, list)
    for obj in objects:
        assert {"id", "frames_seen", "points_per_frame", "poses", "poses_sensor", "extent"} <= set(obj)
        assert len(obj["poses"]) == 3
    got = fitted.poses()
    assert got.shape == (3, 4, 4)
    np.testing.assert_allclose(got, poses, atol=1e-9)


def test_unknown_job_is_not_found(client):
    with pytest.raises(NotFound) as caught:
        client.job(UNKNOWN_JOB)
    e = caught.value
    assert e.status == 404
    assert e.type == "urn:mbnt:problem:not-found"
    assert e.slug == "not-found"
    assert isinstance(e.title, str) and e.title
    assert isinstance(e.detail, str) and e.detail
    assert e.problem["status"] == 404
    assert isinstance(e, mbnt_client.ApiError)
    with pytest.raises(NotFound):
        client.sequence(UNKNOWN_JOB)
    with pytest.raises(NotFound):  # the event stream's 404 is raised, not waited out
        client_module.Job(client, {"id": UNKNOWN_JOB, "status": "queued"}).wait(progress=False, timeout=10)


def test_bad_params_name_the_parameter(client, sequence):
    with pytest.raises(ValidationError) as caught:
        client.fit(sequence.id, params={"learning_rate": 5.0})
    assert caught.value.status == 422
    assert caught.value.type == "urn:mbnt:problem:invalid-input"
    assert caught.value.parameter == "params.learning_rate"
    assert "params.learning_rate" in str(caught.value)
    with pytest.raises(ValidationError) as caught:
        client.fit(sequence.id, params={"no_such_param": 1})
    assert caught.value.parameter == "params.no_such_param"
    with pytest.raises(ValidationError) as caught:
        client.fit(sequence.id, method="no-such-method")
    assert caught.value.parameter == "method"
    with pytest.raises(LimitExceeded) as caught:
        client.fit(sequence.id, params={"iterations": 1000})
    assert caught.value.limit == "max_iterations"


def test_query_errors(fitted, scene):
    with pytest.raises(ValidationError) as caught:
        fitted.query(3, times=[0.0])
    assert caught.value.parameter == "frame"
    with pytest.raises(ValidationError) as caught:
        fitted.query(0, indices=[0], times=[5.0])
    assert caught.value.parameter == "times"
    with pytest.raises(PayloadTooLarge) as caught:  # about 5.5 KB of JSON, over --max-json-bytes (4096)
        fitted.query_points(np.full((150, 3), 1.2345678), t=0.0, times=[0.0])
    assert caught.value.status == 413
    with pytest.raises(Conflict):
        fitted.cancel()  # a succeeded job cannot be cancelled


def test_upload_from_files(client, scene, tmp_path):
    frames, _ = scene
    npy = tmp_path / "000000.npy"
    np.save(npy, frames[0])
    kitti = tmp_path / "000001.bin"
    xyzr = np.concatenate([frames[1], np.zeros((len(frames[1]), 1), np.float32)], axis=1)
    xyzr.astype("<f4").tofile(kitti)
    seq = client.upload([npy, str(kitti), frames[2].astype(np.float64)])
    assert seq.points_per_frame == [len(f) for f in frames]
    assert seq.time_unit == "frame" and seq.timestamps == [0, 1, 2]
    assert not seq.has_poses
    job = seq.fit("ntp", params={"iterations": 1, "hidden_width": 4, "hidden_layers": 1})
    job.wait(progress=False, timeout=60)
    for k, frame in enumerate(frames):
        np.testing.assert_allclose(job.query(k, times=[k])[:, 0, :], frame, atol=1e-4)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nthis is not a point cloud\n")
    with pytest.raises(ValidationError) as caught:
        client.upload([npy, garbage])
    assert caught.value.parameter == "frame"
    assert "garbage.ply" in caught.value.detail
    with pytest.raises(ValueError):
        client.upload([np.zeros((4, 2)), np.zeros((4, 2))])


def test_wait_falls_back_to_polling_when_the_stream_ends_early(client, sequence, monkeypatch):
    real_events = client_module._sse.events

    def first_event_only(chunks):
        for event in real_events(chunks):
            yield event
            return

    monkeypatch.setattr(client_module._sse, "events", first_event_only)
    job = sequence.fit("ntp", params={"iterations": 5, "hidden_width": 8, "hidden_layers": 1})
    final = job.wait(progress=False, timeout=60, poll_interval=0.1)
    assert final["status"] == "succeeded"
    assert job.status == "succeeded"


def test_wait_timeout_then_cancel(client, sequence):
    # About 7 s of fitting on one thread: far longer than the wait's timeout.
    job = sequence.fit("mbnt", params={"iterations": 50, "hidden_width": 256, "hidden_layers": 8, "sample_points": 0})
    started = time.monotonic()
    with pytest.raises(WaitTimeout) as caught:
        job.wait(progress=False, timeout=0.3)
    assert time.monotonic() - started < 3.0
    assert caught.value.job["status"] in ("queued", "running")
    assert isinstance(caught.value, TimeoutError)
    assert job.cancel()["status"] in ("cancelled", "running")
    with pytest.raises(JobCancelled) as caught:
        job.wait(progress=False, timeout=60)
    assert caught.value.job["status"] == "cancelled"
    assert job.status == "cancelled"


def test_wait_with_a_progress_bar_off_a_tty(client, sequence, server_url):
    """wait(progress=True) in a process whose stdout and stderr are pipes (no TTY)."""
    job = sequence.fit("mbnt", params=TINY)
    script = (
        "import sys; from mbnt_client import Client\n"
        "view = Client(sys.argv[1]).job(sys.argv[2]).wait(progress=True, timeout=60)\n"
        "print(view['status'])\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script, server_url, job.id],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, timeout=90,
    )
    assert done.returncode == 0, done.stderr.decode()
    assert done.stdout.decode().strip() == "succeeded"
    bar = done.stderr.decode()
    assert f"job {job.id[:8]}" in bar and "100%" in bar


def test_token_auth():
    token = "test-token-0123456789"
    with running_server(token=token) as url:
        with pytest.raises(Unauthorized) as caught:
            Client(url).sequences()
        assert caught.value.status == 401
        assert caught.value.type == "urn:mbnt:problem:unauthorized"
        with pytest.raises(Unauthorized):
            Client(url, token="wrong").job(UNKNOWN_JOB)
        with Client(url, token=token) as c:
            assert c.sequences() == []
            frames, _ = synthetic_scene()
            seq = c.upload(frames[:2])
            assert [s.id for s in c.sequences()] == [seq.id]
            with pytest.raises(NotFound):
                c.job(UNKNOWN_JOB)
