"""The exception every failed visq call raises."""
import re

import grpc

# The server's messages open with the field they are about ("light.vertices:
# empty", "samples.count: 5000 ..."), or name a server flag for a cap
# ("... the cap of --max-upload-bytes").
_FIELD = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*(?:\[\d+\])?(?:\.[A-Za-z_][A-Za-z0-9_]*(?:\[\d+\])?)*)"
                    r"(?:, [A-Za-z_][A-Za-z0-9_.\[\]]*)*: ")
_FLAG = re.compile(r"(--[a-z][a-z0-9-]*)")


class VisqError(Exception):
    """A visq call failed.

    code:    the grpc.StatusCode (INVALID_ARGUMENT, NOT_FOUND, ...).
    details: the server's message.
    field:   the request field the message names ("samples.count"), or the
             server flag of a cap ("--max-upload-bytes"); None when it names
             neither.
    """

    def __init__(self, code, details, field=None):
        self.code = code
        self.details = details
        self.field = field if field is not None else field_of(details)
        super().__init__(f"{code.name}: {details}")


class Cancelled(VisqError):
    """The call was cancelled by the caller (a Cancellation, or Ctrl-C)."""

    def __init__(self, details="cancelled by the caller"):
        super().__init__(grpc.StatusCode.CANCELLED, details, field=None)


def field_of(details):
    if not details:
        return None
    match = _FIELD.match(details)
    if match:
        return match.group(1)
    match = _FLAG.search(details)
    return match.group(1) if match else None


def from_rpc_error(error):
    """A grpc.RpcError as a VisqError."""
    code = error.code() if hasattr(error, "code") else grpc.StatusCode.UNKNOWN
    details = error.details() if hasattr(error, "details") else str(error)
    return VisqError(code or grpc.StatusCode.UNKNOWN, details or "")
