"""Schemathesis hooks for the contract run in `.ci/schemathesis/run` (SCHEMATHESIS_HOOKS).

Four things the OpenAPI document cannot say by itself:

* Auth depends on how the server was started. The document lists two alternatives on every
  `/v1` operation, `bearer` and `{}` (none). Against a server started with MBNT_API_TOKEN the
  run sets MBNT_ST_AUTH=required, and the `{}` alternative is removed here, so that the
  `ignored_auth` check really probes that requests without the token, or with a wrong one,
  are refused.

* Some 422s answer constraints no JSON Schema can express: the content of an uploaded frame
  file, a value checked against stored data (a sequence id that names no sequence, a frame
  index beyond the fitted sequence, a time outside its time axis), relations between fields
  (as many timestamps as frames, strictly increasing), and the server's configured limits
  (`limit-exceeded`, deliberately low in CI so that any fit a run queues stays short). Each is
  documented in openapi.yaml. A "schema-valid request rejected" failure is dropped only when
  the answer is exactly such a problem (status 422, problem+json, and the `limit` or the
  `parameter` and detail listed below); any other rejection of schema-valid data still fails
  the run. The run's summary counts the dropped failures.

* The stateful phase should reach real sequences and jobs through the document's links, but
  most generated uploads and jobs fall into the 422s above. In that phase only, schema-valid
  JSON uploads and jobs are trimmed to what the server stores and runs (`map_case`).

* Deleting a sequence deletes its finished jobs. `ensure_resource_availability` only knows
  that a DELETE removes the paths below its own, so a job whose sequence a scenario deleted
  would count as "created resource not found". Such a failure is dropped only when the hooks
  saw the job created for that sequence and the sequence deleted (204).
"""

import json
import os

import schemathesis
from schemathesis.openapi.checks import EnsureResourceAvailability, RejectedPositiveData

# (operationId, problem `parameter`, a fragment of `detail`) of the 422s that depend on data
# the schema cannot see.
DATA_DEPENDENT = {
    ("createSequence", "frame", ""),  # a frame file in no readable format, empty, or non-finite
    ("createSequence", "timestamps", "timestamps for"),  # not one per frame
    ("createSequence", "timestamps", "strictly increasing"),
    ("createSequence", "poses", "poses for"),  # not one per frame
    ("createJob", "sequence_id", "no sequence with id"),
    # smaller than window_frames (a relation between two fields); the schema says each one's range
    ("createJob", "params.window_overlap_frames", "must be in [1, "),
    ("queryJob", "frame", "does not exist"),
    ("queryJob", "indices", "out of range"),
    ("queryJob", "t", ""),  # outside the fitted time axis
    ("queryJob", "times", ""),
}


# The server's limits in this run (.ci/schemathesis/run passes its --max-* options; 0: unknown,
# leave the generated bodies alone).
MAX_ITERATIONS = int(os.environ.get("MBNT_ST_MAX_ITERATIONS", "0"))
MAX_FRAMES = int(os.environ.get("MBNT_ST_MAX_FRAMES", "0"))
MAX_POINTS = int(os.environ.get("MBNT_ST_MAX_POINTS_PER_FRAME", "0"))


def _operation_id(case):
    return case.operation.definition.raw.get("operationId")


def _fit_meta(meta, frames):
    """`meta` (a dict) with as many strictly increasing timestamps and poses as `frames`."""
    meta = dict(meta)
    timestamps = meta.get("timestamps")
    if isinstance(timestamps, list) and (
        len(timestamps) != frames or any(b <= a for a, b in zip(timestamps, timestamps[1:]))
    ):
        meta["timestamps"] = [0.1 * k for k in range(frames)]
    poses = meta.get("poses")
    if isinstance(poses, list) and len(poses) != frames:
        identity = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0]
        meta["poses"] = [identity] * frames
    return meta


def _storable_sequence(body):
    """A schema-valid JSON upload changed to one the server stores: within the frame and point
    limits, with one timestamp and pose per frame."""
    if not isinstance(body, dict):
        return body
    # Multipart uploads stay as generated: schemathesis cannot validate binary parts, so a
    # changed one would count as schema-violating.
    if not isinstance(body.get("frames"), list):
        return body
    frames = [f[:MAX_POINTS] if isinstance(f, list) else f for f in body["frames"][:MAX_FRAMES]]
    return _fit_meta({**body, "frames": frames}, len(frames))


def _runnable_job(body):
    """A schema-valid job changed to one within the server's iteration limit, its window overlap
    smaller than its window."""
    if not isinstance(body, dict) or not isinstance(body.get("params", {}), dict):
        return body
    params = dict(body.get("params", {}))
    iterations = params.get("iterations")
    if not isinstance(iterations, int) or iterations > MAX_ITERATIONS:
        params["iterations"] = MAX_ITERATIONS
    # The overlap must be smaller than the window (25 by default), which the schema cannot say.
    overlap = params.get("window_overlap_frames")
    if isinstance(overlap, int) and overlap >= params.get("window_frames", 25):
        params.pop("window_overlap_frames")
    return {**body, "params": params}


@schemathesis.hook
def map_case(context, case):
    """In the stateful phase, keep schema-valid uploads and jobs within what this server stores
    and runs.

    Many generated JSON uploads are not stored (timestamps that do not match the frames, more
    frames than the CI limit) and most jobs ask for more iterations than the CI server allows
    (the default alone, 1001, does). The links from POST /v1/sequences and POST /v1/jobs would
    then mostly lead to resources that do not exist. The stateless phases keep the generated
    values, and with them every 422 above.
    """
    meta = case.meta
    if not (MAX_ITERATIONS and MAX_FRAMES and MAX_POINTS) or meta is None:
        return case
    if meta.phase.name != "stateful" or not meta.generation.mode.is_positive:
        return case
    operation = _operation_id(case)
    if operation == "createSequence":
        case.body = _storable_sequence(case.body)
    elif operation == "createJob":
        case.body = _runnable_job(case.body)
    return case


@schemathesis.hook
def before_load_schema(context, raw_schema):
    if os.environ.get("MBNT_ST_AUTH") != "required":
        return
    for methods in raw_schema.get("paths", {}).values():
        for operation in methods.values():
            if isinstance(operation, dict) and "security" in operation:
                operation["security"] = [s for s in operation["security"] if s]


def _problem(response):
    if response is None or response.status_code != 422:
        return None
    if not response.headers.get("content-type", [""])[0].startswith("application/problem+json"):
        return None
    try:
        return json.loads(response.content)
    except ValueError:
        return None


# Job id -> its sequence id, for every job created in the run; sequence ids deleted (204).
JOB_SEQUENCE = {}
DELETED_SEQUENCES = set()


@schemathesis.hook
def after_call(context, case, response):
    operation = _operation_id(case)
    if operation == "createJob" and response.status_code == 202:
        job = json.loads(response.content)
        JOB_SEQUENCE[job["id"]] = job["sequence_id"]
    elif operation == "deleteSequence" and response.status_code == 204:
        DELETED_SEQUENCES.add(str((case.path_parameters or {}).get("id")))


def _job_deleted_with_its_sequence(case, response):
    if response is None or response.status_code != 404 or not case.path.startswith("/v1/jobs/{id}"):
        return False
    sequence = JOB_SEQUENCE.get(str((case.path_parameters or {}).get("id")))
    return sequence is not None and sequence in DELETED_SEQUENCES


@schemathesis.hook
def filter_failure(context, failure, case, response):
    if isinstance(failure, EnsureResourceAvailability):
        return not _job_deleted_with_its_sequence(case, response)
    if not isinstance(failure, RejectedPositiveData):
        return True
    problem = _problem(response)
    if problem is None:
        return True
    if problem.get("type") == "urn:mbnt:problem:limit-exceeded" and problem.get("limit"):
        return False
    operation_id = _operation_id(case)
    parameter = problem.get("parameter")
    detail = problem.get("detail", "")
    for op, param, fragment in DATA_DEPENDENT:
        if op == operation_id and param == parameter and fragment in detail:
            return False
    return True
