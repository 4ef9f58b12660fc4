"""Is the Tello's H.264 stream intact? Lost and reordered datagrams found, so that no frame decoded from a
damaged stream is used as a clean measurement.

The Tello sends each encoded frame (Annex B) in datagrams of exactly 1460 bytes but the last, which is
shorter (the framing dji-sdk/Tello-Python's h264 example reassembles frames by: it decodes when a
datagram is not 1460 bytes long), and H.264 P frames reference the frame before them, so one lost
datagram spoils every frame up to the next IDR keyframe (users see "all the frames after this frame
infected": SMerrony/tello-desktop#5; smeared, green frames on a weak link: anqixu/tello_driver#6, #7,
dji-sdk/Tello-Python#86). `StreamCheck` finds a loss three ways:

* framing (`datagram`): a datagram that starts a NAL unit (start code) right after a full 1460-byte one
  means the previous frame's tail was lost; one that does not start a NAL unit after a short one means a
  frame's head was lost. If the stream turns out not to be framed that way (more than
  FRAMING_DOUBT of the judged datagrams would be losses after FRAMING_MIN judged), the rule is switched
  off (`counts["framing_off"]`) rather than condemn every frame;
* frame numbers (`access_unit`): each picture's `frame_num` (slice header, with log2_max_frame_num from
  the SPS) must follow the previous reference picture's; a jump means whole frames were lost;
* the decoder (`mark_damaged`): a decode error or a frame the decoder flags corrupt.

From a loss until the next IDR access unit that arrives intact, every access unit is damaged: the
decoder conceals what is missing, so its frames may be smeared (the receiver publishes them tagged
`damaged`, with the frames since the loss, `since_loss`: docs/links.md, "What the receiver does with a
damaged stream"). A stream is unsynchronised until its first intact IDR (`synced`): nothing before it
is a picture. A lost *middle* datagram (a full-length one between two full-length
ones) breaks no framing rule and often no decoder check: such a frame passes as intact, which is why a
detection is checked against a prediction however its frame is tagged (flightstack.vision.gate).
Counters (in the receiver's `counts`): "lost_head", "lost_tail", "frame_gap", "damaged_units", "resync".
Pure: bytes in, verdicts out (no I/O, no decoder).
"""

from __future__ import annotations

from collections import Counter

TELLO_DATAGRAM_BYTES = 1460
"""Payload of every video datagram of a frame but its last."""
FRAMING_MIN = 100
"""Datagrams judged by the framing rule before it may be found not to apply."""
FRAMING_DOUBT = 0.25
"""Fraction of judged datagrams flagged as losses above which the framing rule is switched off."""
_START3 = b"\x00\x00\x01"
_HIGH_PROFILES = frozenset({100, 110, 122, 244, 44, 83, 86, 118, 128, 138, 139, 134, 135})


def _starts_nal(data: bytes) -> bool:
    return data.startswith(_START3) or data.startswith(b"\x00" + _START3)


def split_nals(au: bytes) -> list[bytes]:
    """The NAL units of an Annex-B byte string (start codes removed; leading bytes before the first
    start code are dropped)."""
    out, i = [], au.find(_START3)
    while i >= 0:
        j = au.find(_START3, i + 3)
        nal = au[i + 3 : j if j >= 0 else len(au)]
        if j >= 0 and nal.endswith(b"\x00"):  # the 4-byte start code's leading zero
            nal = nal[:-1]
        out.append(nal)
        i = j
    return out


class _Bits:
    """An exp-Golomb bit reader over a NAL unit's RBSP (emulation prevention bytes removed)."""

    def __init__(self, nal: bytes, limit: int = 64) -> None:
        raw = nal[1 : 1 + limit]
        self.data = raw.replace(b"\x00\x00\x03", b"\x00\x00")
        self.pos = 0

    def u(self, n: int) -> int:
        v = 0
        for _ in range(n):
            byte = self.data[self.pos >> 3]  # IndexError past the end: the caller gives up
            v = (v << 1) | ((byte >> (7 - (self.pos & 7))) & 1)
            self.pos += 1
        return v

    def ue(self) -> int:
        zeros = 0
        while self.u(1) == 0:
            zeros += 1
            if zeros > 31:
                raise ValueError("bad exp-Golomb code")
        return (1 << zeros) - 1 + self.u(zeros)


def sps_frame_num_bits(nal: bytes) -> tuple[int, bool] | None:
    """(log2_max_frame_num, separate_colour_plane) of an SPS NAL unit; None when it cannot be read."""
    try:
        b = _Bits(nal)
        profile_idc = b.u(8)
        b.u(16)  # constraint flags, level_idc
        b.ue()  # seq_parameter_set_id
        separate = False
        if profile_idc in _HIGH_PROFILES:
            if b.ue() == 3:  # chroma_format_idc
                separate = bool(b.u(1))
            b.ue()  # bit_depth_luma_minus8
            b.ue()  # bit_depth_chroma_minus8
            b.u(1)  # qpprime_y_zero_transform_bypass_flag
            if b.u(1):  # seq_scaling_matrix_present_flag: scaling lists not parsed
                return None
        return b.ue() + 4, separate
    except (IndexError, ValueError):
        return None


class StreamCheck:
    """Judges a Tello H.264 stream datagram by datagram and access unit by access unit (module docstring).

    counts: the receiver's counters (updated here)."""

    def __init__(self, counts: Counter[str], datagram_bytes: int = TELLO_DATAGRAM_BYTES) -> None:
        self.counts = counts
        self.datagram_bytes = datagram_bytes
        self.damaged = True  # until the first intact IDR
        self.synced = False  # an intact IDR has arrived: the stream's frames are pictures
        self.since_loss: int | None = None  # access units since the last detected loss (0: this one's)
        self._loss = False  # a loss seen since the last access unit
        self._syncing = False  # the current access unit is the one that synchronised the stream
        self._prev_len: int | None = None
        self._framing_on = True
        self._judged = 0
        self._flagged = 0
        self._frame_num_bits: tuple[int, bool] | None = None
        self._prev_ref_num: int | None = None

    # ---- datagrams ------------------------------------------------------------------------------------
    def datagram(self, data: bytes) -> None:
        """Judge the framing of the next datagram (before it is given to the parser)."""
        prev, self._prev_len = self._prev_len, len(data)
        if prev is None or not self._framing_on:
            return
        starts = _starts_nal(data)
        self._judged += 1
        if starts and prev == self.datagram_bytes:
            self._flag("lost_tail")
        elif not starts and prev < self.datagram_bytes:
            self._flag("lost_head")
        if self._judged >= FRAMING_MIN and self._flagged > FRAMING_DOUBT * self._judged:
            self._framing_on = False  # this stream is not framed as a Tello frames it
            self.counts["framing_off"] += 1

    def _flag(self, what: str) -> None:
        self._flagged += 1
        self.counts[what] += 1
        self._loss = True

    # ---- access units ---------------------------------------------------------------------------------
    def access_unit(self, au: bytes) -> bool:
        """Judge one access unit from the parser; True when its frame may be used (intact stream)."""
        loss, self._loss = self._loss, False
        idr, self._syncing = False, False
        for nal in split_nals(au):
            if not nal:
                continue
            kind, ref_idc = nal[0] & 0x1F, (nal[0] >> 5) & 3
            if kind == 7:
                self._frame_num_bits = sps_frame_num_bits(nal)
            elif kind in (1, 5):
                idr = idr or kind == 5
                loss = self._frame_num_gap(nal, kind == 5, ref_idc) or loss
        if idr and not loss:
            if self.damaged:
                self.counts["resync"] += 1
            self._syncing = not self.synced
            self.damaged, self.synced = False, True
        elif loss:
            self.damaged = True
        self._count_since(loss)
        if self.damaged:
            self.counts["damaged_units"] += 1
        return not self.damaged

    def _frame_num_gap(self, nal: bytes, idr: bool, ref_idc: int) -> bool:
        """True when this slice's frame_num shows lost frames (only the first slice of a picture counts)."""
        bits = self._frame_num_bits
        if bits is None:
            return False
        try:
            b = _Bits(nal)
            if b.ue() != 0:  # first_mb_in_slice: not a picture's first slice
                return False
            b.ue()  # slice_type
            b.ue()  # pic_parameter_set_id
            if bits[1]:
                b.u(2)  # colour_plane_id
            frame_num = b.u(bits[0])
        except (IndexError, ValueError):
            return False
        prev, gap = self._prev_ref_num, False
        if not idr and prev is not None:
            gap = frame_num not in (prev, (prev + 1) % (1 << bits[0]))
            if gap:
                self.counts["frame_gap"] += 1
        if ref_idc:
            self._prev_ref_num = frame_num
        return gap

    def _count_since(self, loss: bool) -> None:
        if loss:
            self.since_loss = 0
        elif self.since_loss is not None:
            self.since_loss += 1

    def mark_damaged(self) -> None:
        """The decoder failed on, or flagged, the current access unit: a loss in it, damaged until the
        next intact IDR."""
        self.damaged = True
        self.since_loss = 0
        if self._syncing:  # the keyframe that was to synchronise the stream did not decode
            self.synced = self._syncing = False


__all__ = ["TELLO_DATAGRAM_BYTES", "StreamCheck", "split_nals", "sps_frame_num_bits"]
