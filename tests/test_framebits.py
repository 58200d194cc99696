"""A frame's bit times on the wire (``host_api.monitor.framebits``), for ``cifemu top``'s load.

Checked against facts that do not come from the module: the CRC-15/CAN check value of the
catalogue of CRCs, a frame worked out by hand, and the worst case of stuffing that the
literature on CAN response times gives for every frame length.
"""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from host_api.monitor.framebits import crc15, frame_bits, stuff_bits


def test_crc15_check_value() -> None:
    """CRC-15/CAN of the ASCII bytes "123456789", most significant bit first, is 0x059E."""
    bits = [(byte >> shift) & 1 for byte in b"123456789" for shift in range(7, -1, -1)]
    assert crc15(bits) == 0x059E


def test_a_stuff_bit_counts_towards_the_next_run() -> None:
    assert stuff_bits([0] * 4) == 0
    assert stuff_bits([0] * 5) == 1
    assert stuff_bits([0] * 5 + [1] * 4) == 2  # the inserted 1 and four more: a run of five
    assert stuff_bits([0, 1] * 20) == 0


def test_the_all_dominant_frame_by_hand() -> None:
    """Identifier 0, no data: SOF to the CRC are 34 dominant bits (the CRC of zeros is 0),
    so a stuff bit after every fifth: 6; then 13 tail bits: 34 + 6 + 13."""
    assert frame_bits(0, b"") == 53


def test_alternating_bits_stuff_at_most_in_the_crc() -> None:
    unstuffed = 47 + 8 * 8
    assert unstuffed <= frame_bits(0x555, bytes([0x55] * 8)) <= unstuffed + 3


@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_standard_frames_lie_between_unstuffed_and_the_worst_case(can_id: int,
                                                                   data: bytes) -> None:
    n = len(data)
    assert 47 + 8 * n <= frame_bits(can_id, data) <= 47 + 8 * n + (34 + 8 * n - 1) // 4


@given(st.integers(0, 0x1FFFFFFF), st.binary(max_size=8))
def test_extended_frames_lie_between_unstuffed_and_the_worst_case(can_id: int,
                                                                   data: bytes) -> None:
    n = len(data)
    bits = frame_bits(can_id, data, extended=True)
    assert 67 + 8 * n <= bits <= 67 + 8 * n + (54 + 8 * n - 1) // 4


def test_a_remote_frame_carries_no_data_but_its_length_code() -> None:
    assert frame_bits(0x701, b"", remote=True, dlc=1) != frame_bits(0x701, b"\0")
    assert 47 <= frame_bits(0x701, b"", remote=True, dlc=1) <= 47 + 8
