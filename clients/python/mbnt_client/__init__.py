"""Python client of the mbnt LiDAR scene-flow service (``mbnt serve``).

    from mbnt_client import Client
    client = Client("http://127.0.0.1:8080")
    seq = client.upload([frame0, frame1, frame2], timestamps=[0.0, 0.1, 0.2])
    job = client.fit(seq.id, params={"iterations": 200})
    job.wait()
    positions = job.query(frame=0, indices=[0, 1], times=[0.0, 0.2])   # (2, 2, 3)
"""

from .client import Client, Job, Sequence
from .errors import (
    ApiError,
    BadRequest,
    Conflict,
    JobCancelled,
    JobFailed,
    LimitExceeded,
    MbntError,
    NotFound,
    PayloadTooLarge,
    ServerError,
    Unauthorized,
    UnsupportedMediaType,
    ValidationError,
    WaitTimeout,
)

__version__ = "0.1.0"

__all__ = [
    "ApiError",
    "BadRequest",
    "Client",
    "Conflict",
    "Job",
    "JobCancelled",
    "JobFailed",
    "LimitExceeded",
    "MbntError",
    "NotFound",
    "PayloadTooLarge",
    "Sequence",
    "ServerError",
    "Unauthorized",
    "UnsupportedMediaType",
    "ValidationError",
    "WaitTimeout",
]
