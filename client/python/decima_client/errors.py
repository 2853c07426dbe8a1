"""Typed errors of decima_client.

Every error's str() is the line the `decima` CLI prints on stderr for the same failure
("decima: submit: INVALID_ARGUMENT: spec.regions: ..."; a missing input file, an unreachable
server and a refused token read the same way), and `exit_code` is the CLI's exit code for it.
Errors from the server carry its status code (`code`, a grpc.StatusCode), its message
(`server_message`) and the structured decima.v1.ErrorDetail it attached (`detail`: which
request field, which limit, where to resume), empty when the server attached none.
"""
import grpc

# The CLI's exit codes (client/client_lib.h).
EXIT_ERROR, EXIT_USAGE, EXIT_JOB_FAILED, EXIT_JOB_CANCELLED = 1, 2, 3, 4
EXIT_TIMEOUT, EXIT_NOT_FOUND, EXIT_UNAUTHENTICATED, EXIT_UNAVAILABLE = 5, 6, 7, 8

_ERROR_DETAIL_KEY = "decima-error-bin"


class DecimaError(Exception):
    """Base of every error decima_client raises."""

    exit_code = EXIT_ERROR
    code = None  # grpc.StatusCode for errors from a call, None for local ones

    def __init__(self, message, *, what="", server_message="", detail=None, code=None):
        super().__init__(message)
        self.message = message
        self.what = what  # the operation, as the CLI names it: "submit", "watch jobs/x", ...
        self.server_message = server_message
        if code is not None:
            self.code = code
        if detail is None:
            from .proto import errors_pb2  # generated at build time

            detail = errors_pb2.ErrorDetail()
        self.detail = detail

    def __str__(self):
        return "decima: " + self.message


class InputError(DecimaError):
    """A local input the client refused before calling the server (CLI exit code 2)."""

    exit_code = EXIT_USAGE


class MissingInputError(InputError, FileNotFoundError):
    """The file or folder to submit does not exist."""


class MissingDependencyError(DecimaError):
    """An optional module (numpy, VTK) that the call needs is not installed."""


class RpcError(DecimaError):
    """A call the server (or gRPC) answered with an error status."""


class InvalidArgument(RpcError):
    pass


class DeadlineExceeded(RpcError):
    exit_code = EXIT_TIMEOUT


class NotFound(RpcError):
    exit_code = EXIT_NOT_FOUND


class AlreadyExists(RpcError):
    pass


class PermissionDenied(RpcError):
    exit_code = EXIT_UNAUTHENTICATED


class Unauthenticated(RpcError):
    exit_code = EXIT_UNAUTHENTICATED


class ResourceExhausted(RpcError):
    pass


class FailedPrecondition(RpcError):
    pass


class Aborted(RpcError):
    pass


class OutOfRange(RpcError):
    pass


class Unimplemented(RpcError):
    pass


class Internal(RpcError):
    pass


class Unavailable(RpcError):
    exit_code = EXIT_UNAVAILABLE


class ServerUnreachable(Unavailable):
    """Nothing answered at the address before the first call (CLI: "cannot reach ...")."""


class DataLoss(RpcError):
    pass


class Cancelled(RpcError):
    pass


class Unknown(RpcError):
    pass


class JobError(DecimaError):
    """A job ended in a state other than SUCCEEDED. `job` is its last decima.v1.Job."""

    def __init__(self, message, *, job=None, **kw):
        super().__init__(message, **kw)
        self.job = job


class JobFailed(JobError):
    exit_code = EXIT_JOB_FAILED


class JobCancelled(JobError):
    exit_code = EXIT_JOB_CANCELLED


_BY_CODE = {
    grpc.StatusCode.CANCELLED: Cancelled,
    grpc.StatusCode.UNKNOWN: Unknown,
    grpc.StatusCode.INVALID_ARGUMENT: InvalidArgument,
    grpc.StatusCode.DEADLINE_EXCEEDED: DeadlineExceeded,
    grpc.StatusCode.NOT_FOUND: NotFound,
    grpc.StatusCode.ALREADY_EXISTS: AlreadyExists,
    grpc.StatusCode.PERMISSION_DENIED: PermissionDenied,
    grpc.StatusCode.RESOURCE_EXHAUSTED: ResourceExhausted,
    grpc.StatusCode.FAILED_PRECONDITION: FailedPrecondition,
    grpc.StatusCode.ABORTED: Aborted,
    grpc.StatusCode.OUT_OF_RANGE: OutOfRange,
    grpc.StatusCode.UNIMPLEMENTED: Unimplemented,
    grpc.StatusCode.INTERNAL: Internal,
    grpc.StatusCode.UNAVAILABLE: Unavailable,
    grpc.StatusCode.DATA_LOSS: DataLoss,
    grpc.StatusCode.UNAUTHENTICATED: Unauthenticated,
}


def error_detail(rpc_error):
    """The decima.v1.ErrorDetail of a failed call (trailing metadata "decima-error-bin"); an
    empty one when the server attached none or it does not parse."""
    from .proto import errors_pb2

    detail = errors_pb2.ErrorDetail()
    trailing = getattr(rpc_error, "trailing_metadata", None)
    for key, value in (trailing() if callable(trailing) else None) or ():
        if key == _ERROR_DETAIL_KEY and isinstance(value, bytes):
            try:
                detail.ParseFromString(value)
            except Exception:  # a detail that does not parse loses nothing: the message stays
                detail.Clear()
    return detail


def from_status(code, server_message, what, detail=None):
    """The typed error for a status: "WHAT: CODE: message", as the CLI's Report prints it."""
    cls = _BY_CODE.get(code, Unknown)
    return cls(f"{what}: {code.name}: {server_message}", what=what,
               server_message=server_message, detail=detail, code=code)


def from_rpc_error(e, what):
    """The typed error for a grpc.RpcError raised by a call."""
    code = e.code() if callable(getattr(e, "code", None)) else grpc.StatusCode.UNKNOWN
    details = e.details() if callable(getattr(e, "details", None)) else str(e)
    return from_status(code, details or "", what, error_detail(e))
