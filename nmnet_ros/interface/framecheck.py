"""The checks a frame passes before it enters the front end, one set for the node and the replay: a stamp that goes
forward (or jumps back far enough to start a new chain), and a calibration that fits the frame's size. Each refusal
carries the warning kind the node counts in /diagnostics (``warn_<kind>``), so a replay's summary names the same."""

from __future__ import annotations

from dataclasses import dataclass

from ..core.geometry import Camera, CameraError
from ..core.pipeline import stamp_order, stamp_warning
from .caminfo import fit_camera


@dataclass(frozen=True)
class Refusal:
    """What to say about a frame, by the node's warning kind."""

    kind: str
    text: str


class FrameChecks:
    """The stamp and calibration checks of one stream of frames (they remember its last stamp and size)."""

    def __init__(self, arrival: str = "stamp_source:=arrival") -> None:
        """``arrival``: how to stamp frames on arrival instead, where a warning says so (the node's parameter, the
        replay's option)."""
        self.arrival = arrival
        self.last_stamp: float | None = None
        self.size: tuple[int, int] | None = None

    def stamp(self, stamp: float, time_jump_s: float) -> tuple[bool, Refusal | None]:
        """Whether the frame stamped ``stamp`` goes on, and what to say: a duplicate, out-of-order, negative or
        invalid stamp is skipped; a jump back by more than ``time_jump_s`` goes on and starts a new chain."""
        kind = stamp_order(self.last_stamp, stamp, time_jump_s)
        if kind is None:
            return True, None
        return kind == "time_jump", Refusal(kind, stamp_warning(kind, self.last_stamp, stamp, self.arrival))

    def camera(self, calibration: Camera, size: tuple[int, int], stamp: float) -> tuple[Camera | None, list[Refusal]]:
        """The camera to process a frame of ``size`` (w, h) with (None: skip it), and what to say; the frame is taken
        as the stream's last (its stamp and size). A new size restarts the chain; a calibration for another size is
        scaled when the frame is it scaled evenly, else refused; one without a size is checked against the frame's."""
        said = []
        if self.size is not None and size != self.size:
            said.append(Refusal("size_changed", f"frame size changed {self.size[0]}x{self.size[1]} -> {size[0]}x{size[1]}: "
                                                "restarting from this frame"))
        self.size, self.last_stamp = size, stamp
        try:
            cam, note = fit_camera(calibration, size)
        except CameraError as e:  # a calibration without a size (fx..cy parameters), implausible for these frames
            return None, [*said, Refusal("bad_camera_info", f"frame skipped: the calibration does not fit "
                                                            f"{size[0]}x{size[1]} frames: {e}")]
        if note:
            said.append(Refusal("camera_size_mismatch", note))
        return cam, said
