"""CAN 2.0 bit budget: how many bits a frame takes on the wire, and the bus load.

A classical CAN data frame with an 11-bit identifier and ``n`` data bytes has
``47 + 8 n`` bits before stuffing (SOF, identifier, RTR, IDE, r0, DLC, data, CRC-15,
CRC delimiter, ACK slot and delimiter, 7-bit EOF, 3-bit intermission). The
transmitter inserts a complementary stuff bit after five equal bits from SOF to the
end of the CRC, so the worst case adds ``floor((34 + 8 n - 1) / 4)`` bits. For a
frame whose content is known, :func:`frame_bits` computes the exact count (it builds
the bit stream, computes the CRC-15 and stuffs it).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

CRC15_POLY = 0x4599  # x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1
STD_OVERHEAD_BITS = 47  # fixed bits of an 11-bit-ID data frame, interframe space included
EXT_OVERHEAD_BITS = 67  # the same with a 29-bit identifier
STD_STUFFED_REGION = 34  # bits from SOF to the end of the CRC, besides the data
EXT_STUFFED_REGION = 54
TAIL_BITS = 13  # CRC delimiter, ACK slot, ACK delimiter, EOF (7), intermission (3)
STUFF_RUN = 5  # equal bits after which a stuff bit is inserted


def _bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def _crc15(bits: list[int]) -> int:
    crc = 0
    for bit in bits:
        top = ((crc >> 14) & 1) ^ bit
        crc = (crc << 1) & 0x7FFF
        if top:
            crc ^= CRC15_POLY
    return crc


def _stuffed_length(bits: list[int]) -> int:
    count = len(bits)
    run_bit = -1
    run = 0
    for bit in bits:
        if bit == run_bit:
            run += 1
        else:
            run_bit, run = bit, 1
        if run == STUFF_RUN:
            count += 1
            run_bit, run = 1 - bit, 1  # the stuff bit starts the next run
    return count


def frame_bits(can_id: int, data: bytes, extended: bool = False) -> int:
    """Exact bits on the wire of one data frame (stuffing and intermission included)."""
    dlc = len(data)
    if dlc > 8:
        raise ValueError("classical CAN carries at most 8 data bytes")
    if extended:
        head = [0] + _bits(can_id >> 18, 11) + [1, 1] + _bits(can_id & 0x3FFFF, 18) + [0, 0, 0]
    else:
        if can_id > 0x7FF:
            raise ValueError(f"0x{can_id:X} is not an 11-bit identifier")
        head = [0] + _bits(can_id, 11) + [0, 0, 0]
    stream = head + _bits(dlc, 4)
    for byte in data:
        stream += _bits(byte, 8)
    stream += _bits(_crc15(stream), 15)
    return _stuffed_length(stream) + TAIL_BITS


def worst_case_bits(n_bytes: int, extended: bool = False) -> int:
    """Bits of a frame with ``n_bytes`` data bytes under maximal stuffing."""
    overhead, region = (EXT_OVERHEAD_BITS, EXT_STUFFED_REGION) if extended else (STD_OVERHEAD_BITS, STD_STUFFED_REGION)
    return overhead + 8 * n_bytes + (region + 8 * n_bytes - 1) // 4


def unstuffed_bits(n_bytes: int, extended: bool = False) -> int:
    return (EXT_OVERHEAD_BITS if extended else STD_OVERHEAD_BITS) + 8 * n_bytes


@dataclass(frozen=True)
class TrafficItem:
    """A periodic frame: ``count`` frames of ``n_bytes`` data bytes at ``rate_hz`` each."""

    label: str
    n_bytes: int
    rate_hz: float
    count: int = 1


@dataclass(frozen=True)
class BusLoad:
    bitrate: int
    nominal_bits_per_s: float  # without stuffing
    worst_bits_per_s: float  # with maximal stuffing

    @property
    def nominal(self) -> float:
        """Fraction of the bus time used, no stuffing."""
        return self.nominal_bits_per_s / self.bitrate

    @property
    def worst(self) -> float:
        """Fraction of the bus time used under maximal stuffing."""
        return self.worst_bits_per_s / self.bitrate


def bus_load(items: Iterable[TrafficItem], bitrate: int) -> BusLoad:
    nominal = worst = 0.0
    for item in items:
        per_s = item.rate_hz * item.count
        nominal += per_s * unstuffed_bits(item.n_bytes)
        worst += per_s * worst_case_bits(item.n_bytes)
    return BusLoad(bitrate, nominal, worst)


class LoadMeter:
    """Bus load of the frames actually seen (call :meth:`add` for each frame).

    Counting is cheap enough for every frame at 1 kHz: frames are counted per
    (identifier, length) and every ``SAMPLE_EVERY``-th payload of each is kept;
    :attr:`bits` multiplies each count by the mean exact length (CRC and stuffing
    computed) of its sampled payloads, so the figure carries the real stuffing.
    """

    SAMPLE_EVERY = 16
    SAMPLES_MAX = 256

    def __init__(self) -> None:
        self.frames = 0
        self._counts: dict[tuple[int, int], int] = {}
        self._samples: dict[tuple[int, int], list[int]] = {}

    def add(self, can_id: int, data: bytes, extended: bool = False) -> None:
        key = (can_id | (1 << 31 if extended else 0), len(data))
        n = self._counts.get(key, 0)
        self._counts[key] = n + 1
        self.frames += 1
        if n % self.SAMPLE_EVERY == 0:
            samples = self._samples.setdefault(key, [])
            if len(samples) < self.SAMPLES_MAX:
                samples.append(frame_bits(can_id, data, extended))

    @property
    def bits(self) -> float:
        total = 0.0
        for key, count in self._counts.items():
            samples = self._samples[key]
            total += count * sum(samples) / len(samples)
        return total

    def reset(self) -> None:
        self.frames = 0
        self._counts.clear()
        self._samples.clear()

    def load(self, elapsed_s: float, bitrate: int) -> float:
        return self.bits / (elapsed_s * bitrate) if elapsed_s > 0 else 0.0
