"""Typed exceptions of the client.

Every non-2xx answer of the service is ``application/problem+json`` (RFC 9457); the client raises
it as an :class:`ApiError` subclass chosen by the status (and, for 422, by the problem ``type``).
"""

from typing import Any, Dict, Optional

import requests

PROBLEM_TYPE_PREFIX = "urn:mbnt:problem:"


class MbntError(Exception):
    """Base of every exception this package raises on purpose."""


class ApiError(MbntError):
    """A non-2xx answer of the service.

    Attributes:
        status: the HTTP status code.
        type: the problem ``type`` (``urn:mbnt:problem:<slug>``).
        title: the problem ``title``.
        detail: the problem ``detail``.
        parameter: the field or hyper-parameter at fault (422 ``invalid-input``), else ``None``.
        limit: the server option exceeded (422 ``limit-exceeded``), else ``None``.
        problem: the whole problem document as a dict.
    """

    def __init__(self, status: int, problem: Dict[str, Any]):
        self.status = status
        self.problem = problem
        self.type: Optional[str] = problem.get("type")
        self.title: Optional[str] = problem.get("title")
        self.detail: Optional[str] = problem.get("detail")
        self.parameter: Optional[str] = problem.get("parameter")
        self.limit: Optional[str] = problem.get("limit")
        message = f"{status} {self.title or ''}: {self.detail or ''}".strip()
        if self.parameter:
            message += f" (parameter: {self.parameter})"
        if self.limit:
            message += f" (limit: {self.limit})"
        super().__init__(message)

    @property
    def slug(self) -> Optional[str]:
        """The problem type without its ``urn:mbnt:problem:`` prefix (e.g. ``not-found``)."""
        if self.type and self.type.startswith(PROBLEM_TYPE_PREFIX):
            return self.type[len(PROBLEM_TYPE_PREFIX):]
        return self.type


class BadRequest(ApiError):
    """400: the request could not be read (malformed JSON or multipart)."""


class Unauthorized(ApiError):
    """401: a missing or wrong bearer token."""


class NotFound(ApiError):
    """404: no such sequence or job."""


class Conflict(ApiError):
    """409: the resource's state does not allow the request (e.g. querying an unfinished job)."""


class PayloadTooLarge(ApiError):
    """413: the body exceeds the server's ``--max-body-bytes`` or ``--max-json-bytes``."""


class UnsupportedMediaType(ApiError):
    """415: the body's content type is not accepted by the route."""


class ValidationError(ApiError):
    """422 ``invalid-input``: a value is not acceptable; :attr:`parameter` names it."""


class LimitExceeded(ValidationError):
    """422 ``limit-exceeded``: a server limit is exceeded; :attr:`limit` names the option."""


class ServerError(ApiError):
    """5xx: the server failed, lacks a feature (501) or its storage does not answer (503)."""


class JobFailed(MbntError):
    """A waited-for job ended ``failed``; :attr:`error` is the job's error, :attr:`job` its view."""

    def __init__(self, job: Dict[str, Any]):
        self.job = job
        self.error: Optional[str] = job.get("error")
        super().__init__(f"job {job.get('id')} failed: {self.error}")


class JobCancelled(MbntError):
    """A waited-for job ended ``cancelled``; :attr:`job` is its final view."""

    def __init__(self, job: Dict[str, Any]):
        self.job = job
        super().__init__(f"job {job.get('id')} was cancelled")


class WaitTimeout(MbntError, TimeoutError):
    """``Job.wait(timeout=...)`` ran out of time; :attr:`job` is the last view seen."""

    def __init__(self, job: Dict[str, Any], timeout: float):
        self.job = job
        super().__init__(f"job {job.get('id')} still {job.get('status')} after {timeout} s")


_BY_STATUS = {
    400: BadRequest,
    401: Unauthorized,
    404: NotFound,
    409: Conflict,
    413: PayloadTooLarge,
    415: UnsupportedMediaType,
    422: ValidationError,
}


def error_from_response(response: requests.Response) -> ApiError:
    """The typed exception for a non-2xx ``response`` (its problem+json, or one made from its text)."""
    problem: Any = None
    try:
        problem = response.json()
    except ValueError:
        pass
    if not isinstance(problem, dict):
        problem = {
            "type": "about:blank",
            "title": response.reason or "",
            "status": response.status_code,
            "detail": response.text[:2000],
        }
    status = response.status_code
    if status >= 500:
        cls = ServerError
    elif status == 422 and problem.get("type") == PROBLEM_TYPE_PREFIX + "limit-exceeded":
        cls = LimitExceeded
    else:
        cls = _BY_STATUS.get(status, ApiError)
    return cls(status, problem)
