"""The WebSocket stream's binary messages: the map is encoded once per frame, exactly as numpy would."""

import time

import numpy as np

from uwcam.api import HEADER, encode_range, range_millimetres
from uwcam.drivers.base import Frame
from uwcam.runtime.published import Published
from uwcam.ranging.result import RangeResult


def published(number: int, range_m: np.ndarray) -> Published:
    h, w = range_m.shape
    frame = Frame(data=np.zeros((h, w, 3), np.uint16), sequence=number, host_monotonic_ns=time.monotonic_ns(),
                  wall_time=time.time())
    result = RangeResult(range_m, np.zeros_like(range_m), np.zeros((h, w), np.uint8))
    return Published(number, frame, result, time.monotonic_ns(), (0.0, 0.1, 0.2))


def test_float16_body_has_numpy_bits_and_is_shared_between_clients():
    rng = np.random.default_rng(1)
    r = rng.uniform(0.2, 30.0, (37, 61)).astype(np.float32)
    r[0, :8] = [np.nan, -0.0, 0.0, 7e4, 1e-7, 2.0**-20, np.inf, 65504.0]  # NaN, signed zero, overflow, subnormals
    p = published(7, r)
    first, second = encode_range(p, "float16"), encode_range(p, "float16")
    magic, number, captured, sent, w, h, dtype, scale = HEADER.unpack_from(first)
    assert (magic, number, w, h, dtype, scale) == (b"UWR1", 7, 61, 37, 1, 1.0)
    with np.errstate(over="ignore"):  # 7e4 m overflows float16 to inf, as intended
        want = r.astype("<f2").tobytes()
    assert first[HEADER.size:] == want == second[HEADER.size:]
    assert HEADER.unpack_from(second)[3] >= sent  # each client's header carries its own send time


def test_each_frame_and_encoding_gets_its_own_body():
    a = published(1, np.full((4, 5), 1.5, np.float32))
    b = published(2, np.full((4, 5), 2.5, np.float32))
    assert encode_range(a, "float16")[HEADER.size:] == a.result.range.astype("<f2").tobytes()
    assert encode_range(b, "float16")[HEADER.size:] == b.result.range.astype("<f2").tobytes()
    assert encode_range(b, "mm")[HEADER.size:] == range_millimetres(b.result.range).tobytes()
    assert encode_range(b, "float16")[HEADER.size:] == b.result.range.astype("<f2").tobytes()
