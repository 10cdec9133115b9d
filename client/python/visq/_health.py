"""grpc.health.v1.Health/Check, its two one-field messages encoded by hand.

Generated stubs for proto/grpc/health/v1 would be a top-level `grpc.health`
package inside grpcio's own `grpc`, and would register grpc.health.v1 in the
default descriptor pool, where Debian's or PyPI's grpcio-health-checking may
register it too. HealthCheckRequest is {string service = 1} and
HealthCheckResponse {ServingStatus status = 1}: a few bytes each.
"""

SERVING_STATUS = {0: "UNKNOWN", 1: "SERVING", 2: "NOT_SERVING", 3: "SERVICE_UNKNOWN"}
METHOD = "/grpc.health.v1.Health/Check"


def _varint(value):
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def encode_request(service):
    data = service.encode("utf-8")
    return b"\x0a" + _varint(len(data)) + data if data else b""


def decode_response(data):
    """The status name; fields other than 1 (none today) are skipped."""
    status, i = 0, 0
    while i < len(data):
        key, i = _read_varint(data, i)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _read_varint(data, i)
            if field == 1:
                status = value
        elif wire == 2:
            length, i = _read_varint(data, i)
            i += length
        elif wire == 1:
            i += 8
        elif wire == 5:
            i += 4
        else:
            raise ValueError(f"HealthCheckResponse: wire type {wire} not understood")
    return SERVING_STATUS.get(status, f"STATUS_{status}")


def _read_varint(data, i):
    shift, value = 0, 0
    while True:
        if i >= len(data):
            raise ValueError("HealthCheckResponse: truncated varint")
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, i
        shift += 7
