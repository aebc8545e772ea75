"""The scene model's validation: value limits, InvalidRecord and the checks every record runs on
construction (rigid transforms, times, image sizes, intrinsics).

The scene model as a whole: :mod:`phigenesis.data.records`."""

from __future__ import annotations

import bisect
import io
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from phigenesis.data import image_headers

BoxStatus = Literal["annotated", "interpolated", "extrapolated"]
BOX_STATUSES: tuple[BoxStatus, ...] = ("annotated", "interpolated", "extrapolated")
ImageFormat = Literal["jpeg", "png"]
IMAGE_FORMATS: tuple[ImageFormat, ...] = ("jpeg", "png")
#: How a camera reads its pixels out: all at once ("global"), or line by line in a direction.
ReadoutDirection = Literal[
    "global", "top_to_bottom", "left_to_right", "bottom_to_top", "right_to_left", "unknown"
]
READOUT_DIRECTIONS: tuple[ReadoutDirection, ...] = (
    "global",
    "top_to_bottom",
    "left_to_right",
    "bottom_to_top",
    "right_to_left",
    "unknown",
)

# --------------------------------------------------------------------------------------------
# Validation limits: values beyond them are not physical and would overflow later arithmetic
# (float32 LiDAR columns, squared distances), so the records refuse them.

#: Largest ``max |R^T R - I|`` of a rigid transform's rotation block (float32-stored rotations
#: are ~1e-7 off; a scaled or sheared one is far beyond).
RIGID_TOLERANCE = 1e-4
#: Largest coordinate of any position (transform translations, box centres), metres (10,000 km).
MAX_COORDINATE_M = 1e7
#: Largest coordinate of a LiDAR point or ray origin in the ego frame, metres.
MAX_POINT_DISTANCE_M = 1e4
#: Largest box side, metres.
MAX_BOX_SIZE_M = 1e3
#: Largest image side, pixels (bounds what decoding an image or allocating its maps can cost).
MAX_IMAGE_SIDE = 8192
#: Focal lengths lie in this range, pixels.
FOCAL_RANGE_PX = (0.1, 1e6)
#: Largest |principal point| and |skew|, pixels, and largest |distortion coefficient|.
MAX_INTRINSIC_PX = 1e6
MAX_DISTORTION = 1e3
#: A capture (camera image, LiDAR sweep, trigger) lies within this of its frame's (or image's)
#: time, and an exposure or readout lasts at most this long, microseconds.
MAX_SENSOR_OFFSET_MICROS = 5_000_000
#: Times are int64 microseconds.
INT64_MAX = 2**63 - 1
#: Largest |time| a user-given time (a path's keyframe, a trajectory's frame) may have, microseconds
#: (about 146,000 years after 1970): sums and differences of two such times stay within int64.
MAX_USER_MICROS = 2**62

#: :class:`DroppedValues` kinds of the records' own helpers (sources use the same words).
INVALID_POINTS = "LiDAR points with non-finite or out-of-range values"
INVALID_BOXES = "boxes with invalid fields"


class InvalidRecord(ValueError):
    """A record was given an invalid value: the message is ``"<field> <problem>"``, e.g.
    ``box 'abc' size_lwh [nan, 1.8, 1.5] must be finite and in (0, 1000] m``.

    Attributes:
        field: what is invalid, as the record names it (``world_from_ego``, ``box 'abc'``,
            ``camera FRONT timestamp_micros``).
        problem: what is wrong with it, with the offending value (a predicate of ``field``).
        index: the position in the checked sequence (the frame of :func:`check_frame_times`,
            the box of :meth:`Boxes.without_invalid`), None where there is none.

    It is not a :class:`~phigenesis.errors.PhiGenesisError`: it names no file. A source catches
    it and raises its ``SourceError`` naming the file and record; one that escapes a source is
    reported as a toolkit bug.
    """

    def __init__(self, field: str, problem: str, index: int | None = None):
        super().__init__(f"{field} {problem}")
        self.field = field
        self.problem = problem
        self.index = index


def _check_array(
    name: str, value: Any, shape: tuple[int | None, ...], dtype: type | None = None
) -> np.ndarray:
    """Returns ``value`` as an array after checking its shape (None = any size) and dtype."""
    try:
        arr = np.asarray(value) if dtype is None else np.asarray(value, dtype=dtype)
    except (TypeError, ValueError, OverflowError) as e:
        raise InvalidRecord(name, f"is not an array of {np.dtype(dtype).name} ({e})") from None
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=False))
    if not ok:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise InvalidRecord(name, f"must have shape {want}, got {arr.shape}")
    return arr


def _listed(values: NDArray) -> str:
    """A short text of an array's values for messages (at most 16 shown)."""
    flat = np.asarray(values).ravel()
    shown = ", ".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in flat[:16].tolist())
    return f"[{shown}{', ...' if flat.size > 16 else ''}]"


_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def check_transform(name: str, value: Any) -> NDArray[np.float64]:
    """``value`` as a (4, 4) float64 rigid transform ``target_from_source``.

    Raises :class:`InvalidRecord` naming ``name`` if an entry is not finite, the last row is not
    (0, 0, 0, 1), the rotation block is not orthonormal with determinant +1 (within
    :data:`RIGID_TOLERANCE`: a scaled, sheared or mirrored matrix is refused), or the translation
    exceeds :data:`MAX_COORDINATE_M` metres. Sources use it for transforms the scene model does
    not hold (LiDAR extrinsics).
    """
    t = _check_array(name, value, (4, 4), np.float64)
    if not np.all(np.isfinite(t)):
        raise InvalidRecord(name, f"has non-finite entries {_listed(t)}")
    # np.allclose's test (|a - b| <= 1e-8 + 1e-5 |b|) written out: allclose itself costs 0.2 ms a
    # call, and a Waymo frame checks 17 transforms.
    if not (np.abs(t[3] - _LAST_ROW) <= 1e-8 + 1e-5 * _LAST_ROW).all():
        raise InvalidRecord(name, f"is not a rigid transform: last row is {_listed(t[3])}")
    rotation = t[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):
        error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if not error <= RIGID_TOLERANCE:
        raise InvalidRecord(
            name,
            f"is not a rigid transform: its rotation is not orthonormal (max |R^T R - I| = {error:.3g}, "
            f"tolerance {RIGID_TOLERANCE:g}; rows {_listed(rotation)})",
        )
    if np.linalg.det(rotation) < 0:
        raise InvalidRecord(name, "is not a rigid transform: its rotation is a reflection (determinant -1)")
    if np.abs(t[:3, 3]).max() > MAX_COORDINATE_M:
        raise InvalidRecord(name, f"has a translation {_listed(t[:3, 3])} m beyond {MAX_COORDINATE_M:g} m")
    return t


def _check_micros(name: str, value: Any, minimum: int = -INT64_MAX) -> int:
    """``value`` as int microseconds in [minimum, INT64_MAX]; raises naming ``name`` otherwise."""
    if isinstance(value, (float, np.floating)) and not np.isfinite(value):
        raise InvalidRecord(name, f"is {value}, not a time")
    try:
        micros = int(value)
    except (TypeError, ValueError, OverflowError) as e:
        raise InvalidRecord(name, f"is {value!r}, not a time in microseconds ({e})") from None
    if not minimum <= micros <= INT64_MAX:
        what = "negative" if micros < 0 <= minimum else "outside int64"
        raise InvalidRecord(name, f"is {micros} us, {what}")
    return micros


def check_capture_time(
    name: str, timestamp_micros: int, reference_micros: int, reference: str = "its frame's time"
) -> None:
    """Raises :class:`InvalidRecord` naming ``name`` if a capture at ``timestamp_micros`` lies more
    than :data:`MAX_SENSOR_OFFSET_MICROS` from ``reference_micros`` (``reference`` says what that
    is: the frame's time, or for a trigger the image's)."""
    offset = int(timestamp_micros) - int(reference_micros)
    if abs(offset) > MAX_SENSOR_OFFSET_MICROS:
        raise InvalidRecord(
            name,
            f"is {int(timestamp_micros)} us, {offset / 1e6:+.6g} s from {reference} "
            f"{int(reference_micros)} us (at most {MAX_SENSOR_OFFSET_MICROS / 1e6:g} s)",
        )


def check_frame_times(times_micros: Sequence[int], what: str = "frame") -> None:
    """Raises :class:`InvalidRecord` (``index`` = the first bad position) unless the times are
    non-negative int64 microseconds that strictly increase (no duplicates, no steps back).

    ``what`` names an element in the message ("frame", "keyframe"). Sources call it once on their
    index of frame times, before any frame is loaded.
    """
    previous: int | None = None
    for i, t in enumerate(times_micros):
        try:
            micros = _check_micros(f"{what} {i} timestamp_micros", t, minimum=0)
        except InvalidRecord as e:
            raise InvalidRecord(e.field, e.problem, index=i) from None
        if previous is not None and micros <= previous:
            same = "the same as" if micros == previous else "before"
            raise InvalidRecord(
                f"{what} {i} timestamp_micros",
                f"is {micros} us, {same} {what} {i - 1}'s {previous} us (times must strictly increase)",
                index=i,
            )
        previous = micros


def increasing_frames(times_micros: Sequence[int]) -> list[int]:
    """The positions to keep so that the times strictly increase: the longest strictly increasing
    subsequence of the valid (non-negative int64) times, the earliest such positions on ties.

    For ``--on-error skip``: one corrupt time (a duplicate, a step back, a jump far ahead) loses
    that frame only, not every frame after it.
    """
    valid = []
    for i, t in enumerate(times_micros):
        try:
            valid.append((i, _check_micros("t", t, minimum=0)))
        except InvalidRecord:
            continue
    # From the right: longest[j] = length of the longest increasing run that starts at valid[j].
    longest = [0] * len(valid)
    tails: list[int] = []  # negated first times of runs of each length, ascending
    for j in range(len(valid) - 1, -1, -1):
        k = bisect.bisect_left(tails, -valid[j][1])
        if k == len(tails):
            tails.append(-valid[j][1])
        else:
            tails[k] = -valid[j][1]
        longest[j] = k + 1
    # From the left: take the first element that can still start a run of the length needed.
    keep: list[int] = []
    need, previous = max(longest, default=0), -1
    for j, (i, t) in enumerate(valid):
        if need and longest[j] == need and t > previous:
            keep.append(i)
            need, previous = need - 1, t
    return keep


def encoded_image_size(data: bytes, image_format: ImageFormat, name: str = "image_bytes") -> tuple[int, int]:
    """(width, height) in pixels that encoded image bytes declare, read from the header alone.

    Raises :class:`InvalidRecord` naming ``name`` if the bytes are not a ``image_format`` image
    whose header says its size. Sources compare it with the calibration before anything decodes
    the image (a crafted header can declare gigapixels).
    """
    if image_format not in IMAGE_FORMATS:
        raise InvalidRecord(name, f"has image format {image_format!r}, not one of {IMAGE_FORMATS}")
    data = bytes(data)
    read_size = image_headers.jpeg_size if image_format == "jpeg" else image_headers.png_size
    try:
        return read_size(io.BytesIO(data).read)
    except ValueError as e:
        what = f"a {image_format.upper()} image with a readable size"
        raise InvalidRecord(name, f"holds {len(data)} bytes that are not {what} ({e})") from None


def _check_intrinsics(name: str, k: NDArray[np.float64]) -> None:
    """Raises unless ``k`` is an OpenCV K: focal lengths in :data:`FOCAL_RANGE_PX`, finite
    principal point and skew within :data:`MAX_INTRINSIC_PX`, bottom rows (0, fy, cy), (0, 0, 1)."""
    if not np.all(np.isfinite(k)):
        raise InvalidRecord(name, f"has non-finite entries {_listed(k)}")
    lo, hi = FOCAL_RANGE_PX
    for label, f in (("fx", k[0, 0]), ("fy", k[1, 1])):
        if not lo <= f <= hi:
            raise InvalidRecord(name, f"has focal length {label} = {f:.6g} px, not in [{lo:g}, {hi:g}]")
    if max(abs(k[0, 1]), abs(k[0, 2]), abs(k[1, 2])) > MAX_INTRINSIC_PX:
        raise InvalidRecord(
            name, f"has a principal point or skew beyond {MAX_INTRINSIC_PX:g} px: {_listed(k)}"
        )
    if k[1, 0] != 0 or not np.array_equal(k[2], [0.0, 0.0, 1.0]):
        raise InvalidRecord(name, f"is not an upper-triangular K with last row (0, 0, 1): {_listed(k)}")
