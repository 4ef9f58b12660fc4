"""The camera calibration file: intrinsics, lens distortion, image kind, what the camera finds on the target.

One YAML file per camera (written by `flightstack calibrate`, read by missions and the sim renderer):

    device: tello-1-down         # free text: which camera
    date: '2026-11-22T18:00:00Z'
    width: 320                   # image size in pixels
    height: 240
    camera_matrix: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]   # pixels
    dist_coeffs: [k1, k2, p1, p2, k3]                       # OpenCV's model
    rms_px: 0.31                 # reprojection RMS of the calibration, or null
    pattern:                     # optional: the calibration target (written by `calibrate camera`)
      kind: chessboard           # chessboard | charuco | acircles
      cols: 7                    # inner corners (chessboard), squares (charuco) or circles per row
      rows: 7
      square_m: 0.0195           # square side, or circle spacing (metres)
    views:                       # optional: the views used, with their reprojection RMS (pixels)
      - {name: left01.jpg, error_px: 0.41}
    image: colour                # colour (default: RGB frames) | grey (one channel: the Tello EDU's
                                 # downward IR camera)
    stream:                      # optional: the decoded frame when the picture is only part of it
      width: 320                 # the frame as the stream delivers it (pixels)
      height: 720
      picture: [0, 0, 320, 240]  # x, y, width, height (pixels) of the picture in it: the crop the driver
                                 # takes; width and height are the calibration's
    markers:                     # EITHER colour discs: one entry per target feature point, in p0^j order
      - name: red
        hsv_lo: [170, 120, 80]   # OpenCV HSV: H in 0..179, S and V in 0..255
        hsv_hi: [8, 255, 255]    # hue wraps around when hsv_lo[0] > hsv_hi[0]
        rgb: [220, 30, 30]       # the colour the simulator paints (optional)
    fiducial:                    # OR one ArUco marker whose four corners are the feature points (m = 4)
      dictionary: DICT_4X4_50    # an OpenCV predefined ArUco dictionary
      id: 0                      # the marker's id in it
      side_m: 0.2                # side of the marker, outer edge of its black border (metres)
      corners: [1, 0, 3, 2]      # corners[j]: the ArUco corner (0 top-left, 1 top-right, 2 bottom-right,
                                 # 3 bottom-left of the printed marker, upright) that is feature point j
      quiet_zone_m: 0.05         # white margin around the marker on the board (metres; default side / 4)

A camera declares colour `markers` or a `fiducial`, not both; a grey camera cannot tell colour discs apart,
so `image: grey` with `markers` is refused (use a `fiducial`). How the fiducial's corners must match the
experiment's feature points: flightstack.vision.fiducial.placement_problem.

Pixel coordinates follow OpenCV: u to the right, v down, origin at the centre of the top-left pixel. The
principal point (cx, cy) must lie in the image: −0.5 ≤ cx ≤ width − 0.5, −0.5 ≤ cy ≤ height − 0.5.
`save` writes JSON instead of YAML when the file name ends in `.json` (the same mapping); `load_calibration`
reads both (JSON is parsed as YAML).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from flightstack.safe_yaml import LoadError, load_yaml

MAX_IMAGE_PX = 100_000
"""Image width and height at most this (pixels): no camera has 10⁵ pixels on a side."""


class CalibrationError(ValueError):
    """A calibration file that cannot be used; the message names the key and the reason."""


@dataclass(frozen=True)
class MarkerColour:
    """HSV thresholds of one marker (OpenCV ranges) and the RGB the simulator paints it with."""

    name: str
    hsv_lo: tuple[int, int, int]
    hsv_hi: tuple[int, int, int]
    rgb: tuple[int, int, int] | None = None

    @property
    def hue_wraps(self) -> bool:
        return self.hsv_lo[0] > self.hsv_hi[0]


IMAGE_KINDS = ("colour", "grey")
"""What a camera's frames hold: `colour` (H × W × 3 RGB uint8) or `grey` (H × W uint8)."""
FIDUCIAL_CORNERS = 4
"""Feature points of a fiducial: its four corners (the paper's m = 4)."""
DEFAULT_QUIET_ZONE = 0.25
"""A fiducial's default quiet zone, as a fraction of its side (white margin on each side of the marker)."""


@dataclass(frozen=True)
class StreamLayout:
    """Where the picture lies in the frame the camera's stream delivers (pixels, OpenCV convention).

    width, height: the decoded frame's size; x, y: the picture's top-left pixel in it; the picture's size is
    the calibration's width × height (the crop `flightstack.drivers.tello.camera.TelloCamera` takes).
    """

    width: int
    height: int
    x: int
    y: int


@dataclass(frozen=True)
class Fiducial:
    """One OpenCV ArUco marker on the target; its four corners are the feature points.

    dictionary: the name of an OpenCV predefined dictionary (cv2.aruco.DICT_*); id: the marker's id in it;
    side_m: the marker's side, the outer edge of its black border (m); corners[j]: the ArUco corner (0
    top-left, 1 top-right, 2 bottom-right, 3 bottom-left of the upright printed marker, OpenCV's order)
    that is feature point j; quiet_zone_m: the white margin around it on the board (m).
    """

    dictionary: str
    id: int
    side_m: float
    corners: tuple[int, int, int, int]
    quiet_zone_m: float


@dataclass(frozen=True)
class CameraCalibration:
    width: int
    height: int
    camera_matrix: np.ndarray  # (3, 3), pixels
    dist_coeffs: np.ndarray  # (n,), OpenCV order k1, k2, p1, p2[, k3, ...]
    markers: tuple[MarkerColour, ...] = ()
    rms_px: float | None = None
    device: str = ""
    date: str = field(default_factory=lambda: _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"))
    #: optional: the calibration target {kind, cols, rows, square_m[, marker_m, dictionary]} (metres)
    pattern: dict[str, object] | None = None
    #: optional: (view name, reprojection RMS in px) of every view the intrinsics were fitted to
    views: tuple[tuple[str, float], ...] = ()
    #: what the frames hold: "colour" (RGB) or "grey" (IMAGE_KINDS)
    image: str = "colour"
    #: where the picture lies in the streamed frame; None: the frame is the picture
    stream: StreamLayout | None = None
    #: the target's ArUco marker (its corners are the feature points); None: colour `markers` or nothing
    fiducial: Fiducial | None = None

    @property
    def grey(self) -> bool:
        """True when the camera's frames are grey (H × W), False for RGB (H × W × 3)."""
        return self.image == "grey"

    @property
    def feature_count(self) -> int:
        """How many feature points the camera finds on the target: 4 for a fiducial, else one per marker."""
        return FIDUCIAL_CORNERS if self.fiducial is not None else len(self.markers)

    @property
    def frame_size(self) -> tuple[int, int]:
        """(width, height) in pixels of the frame the stream delivers (the picture's without `stream`)."""
        s = self.stream
        return (self.width, self.height) if s is None else (s.width, s.height)

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def cx(self) -> float:
        return float(self.camera_matrix[0, 2])

    @property
    def cy(self) -> float:
        return float(self.camera_matrix[1, 2])

    def to_dict(self) -> dict[str, object]:
        return {
            "device": self.device,
            "date": self.date,
            "width": int(self.width),
            "height": int(self.height),
            "camera_matrix": np.asarray(self.camera_matrix, dtype=float).tolist(),
            "dist_coeffs": np.asarray(self.dist_coeffs, dtype=float).tolist(),
            "rms_px": None if self.rms_px is None else float(self.rms_px),
            "markers": [
                {
                    "name": m.name,
                    "hsv_lo": list(m.hsv_lo),
                    "hsv_hi": list(m.hsv_hi),
                    **({"rgb": list(m.rgb)} if m.rgb is not None else {}),
                }
                for m in self.markers
            ],
            **({"pattern": dict(self.pattern)} if self.pattern is not None else {}),
            **(
                {"views": [{"name": n, "error_px": round(float(e), 6)} for n, e in self.views]}
                if self.views
                else {}
            ),
            **({"image": self.image} if self.image != "colour" else {}),
            **({"stream": _stream_dict(self.stream, self)} if self.stream is not None else {}),
            **({"fiducial": _fiducial_dict(self.fiducial)} if self.fiducial is not None else {}),
        }

    def save(self, path: str | Path) -> None:
        """Write the calibration (JSON if the name ends in .json, else YAML) atomically: a temporary file
        in the same directory is renamed over `path` only once it is completely written."""
        path = Path(path)
        d = self.to_dict()
        text = (
            json.dumps(d, indent=2) + "\n"
            if path.suffix.lower() == ".json"
            else yaml.safe_dump(d, sort_keys=False)
        )
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


def _stream_dict(s: StreamLayout, cal: CameraCalibration) -> dict[str, object]:
    return {"width": s.width, "height": s.height, "picture": [s.x, s.y, cal.width, cal.height]}


def _fiducial_dict(f: Fiducial) -> dict[str, object]:
    return {
        "dictionary": f.dictionary,
        "id": f.id,
        "side_m": f.side_m,
        "corners": list(f.corners),
        "quiet_zone_m": f.quiet_zone_m,
    }


def _triple(v: object, key: str, hi: int) -> tuple[int, int, int]:
    if not (isinstance(v, list | tuple) and len(v) == 3 and all(isinstance(x, int) for x in v)):
        raise CalibrationError(f"{key}: expected 3 integers, got {v!r}")
    if any(x < 0 or x > hi for x in v):
        raise CalibrationError(f"{key}: values must be in 0..{hi}, got {v!r}")
    return (int(v[0]), int(v[1]), int(v[2]))


def calibration_from_dict(d: object, source: str = "<calibration>") -> CameraCalibration:
    """Validate a parsed calibration document; CalibrationError names the key path and the reason."""
    if not isinstance(d, dict):
        raise CalibrationError(f"{source}: a calibration must be a mapping")
    known = {
        "device",
        "date",
        "width",
        "height",
        "camera_matrix",
        "dist_coeffs",
        "rms_px",
        "markers",
        "pattern",
        "views",
        "image",
        "stream",
        "fiducial",
    }
    for k in d:
        if k not in known:
            raise CalibrationError(f"{source}: {k}: unknown key")
    try:
        w, h = d["width"], d["height"]
        K = np.array(d["camera_matrix"], dtype=float)
        dist = np.array(d.get("dist_coeffs", [0, 0, 0, 0, 0]), dtype=float).reshape(-1)
    except KeyError as exc:
        raise CalibrationError(f"{source}: {exc.args[0]}: missing") from None
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{source}: camera_matrix/dist_coeffs: not numeric ({exc})") from None
    if not (isinstance(w, int) and isinstance(h, int) and 0 < w <= MAX_IMAGE_PX and 0 < h <= MAX_IMAGE_PX):
        raise CalibrationError(f"{source}: width/height: integers in 1..{MAX_IMAGE_PX} (pixels) required")
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1:
        raise CalibrationError(
            f"{source}: camera_matrix: must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with fx, fy > 0"
        )
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
        raise CalibrationError(
            f"{source}: camera_matrix: the principal point (cx, cy) = ({cx:g}, {cy:g}) px lies outside the "
            f"{w} × {h} image (cx in [-0.5, {w - 0.5:g}], cy in [-0.5, {h - 0.5:g}]); width, height or "
            "camera_matrix is wrong"
        )
    if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise CalibrationError(f"{source}: dist_coeffs: 4, 5, 8, 12 or 14 finite numbers required")
    raw_markers = d.get("markers") or []
    if not isinstance(raw_markers, list):
        raise CalibrationError(f"{source}: markers: expected a list of marker colours, got {raw_markers!r}")
    markers = []
    for j, m in enumerate(raw_markers):
        key = f"markers.{j}"
        if not isinstance(m, dict) or set(m) - {"name", "hsv_lo", "hsv_hi", "rgb"}:
            raise CalibrationError(f"{source}: {key}: expected keys name, hsv_lo, hsv_hi[, rgb]")
        lo = _triple(m.get("hsv_lo"), f"{key}.hsv_lo", 255)
        hi = _triple(m.get("hsv_hi"), f"{key}.hsv_hi", 255)
        if lo[0] > 179 or hi[0] > 179:
            raise CalibrationError(f"{source}: {key}: hue must be in 0..179 (OpenCV HSV)")
        rgb = _triple(m["rgb"], f"{key}.rgb", 255) if m.get("rgb") is not None else None
        markers.append(MarkerColour(str(m.get("name", f"marker{j}")), lo, hi, rgb))
    image = d.get("image", "colour")
    if image not in IMAGE_KINDS:
        raise CalibrationError(f"{source}: image: one of {', '.join(IMAGE_KINDS)} required, got {image!r}")
    fiducial = _fiducial(d.get("fiducial"), source)
    if fiducial is not None and markers:
        raise CalibrationError(
            f"{source}: markers: a camera finds either colour markers or a fiducial; remove `markers:` "
            "or `fiducial:`"
        )
    if image == "grey" and markers:
        raise CalibrationError(
            f"{source}: markers: a grey camera (image: grey) cannot tell colour markers apart; declare the "
            "target's ArUco `fiducial:` instead (docs/calibration.md#the-fiducial)"
        )
    rms = d.get("rms_px")
    if rms is not None and not (
        isinstance(rms, int | float) and not isinstance(rms, bool) and math.isfinite(rms) and rms >= 0
    ):
        raise CalibrationError(f"{source}: rms_px: a finite number >= 0 (pixels) or null, got {rms!r}")
    return CameraCalibration(
        w,
        h,
        K,
        dist,
        tuple(markers),
        None if rms is None else float(rms),
        str(d.get("device", "")),
        str(d.get("date", "")),
        _pattern(d.get("pattern"), source),
        _views(d.get("views"), source),
        str(image),
        _stream(d.get("stream"), w, h, source),
        fiducial,
    )


def _count(v: object) -> bool:
    """A non-negative integer (not a bool)."""
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _stream(s: object, w: int, h: int, source: str) -> StreamLayout | None:
    """Validate the optional `stream` mapping {width, height, picture: [x, y, w, h]} (pixels)."""
    if s is None:
        return None
    if not isinstance(s, dict) or set(s) != {"width", "height", "picture"}:
        raise CalibrationError(f"{source}: stream: expected keys width, height, picture (pixels)")
    fw, fh, pic = s["width"], s["height"], s["picture"]
    if not (_count(fw) and _count(fh) and 0 < fw <= MAX_IMAGE_PX and 0 < fh <= MAX_IMAGE_PX):
        raise CalibrationError(
            f"{source}: stream.width/height: integers in 1..{MAX_IMAGE_PX} (pixels) required"
        )
    if not (isinstance(pic, list) and len(pic) == 4 and all(_count(v) for v in pic)):
        raise CalibrationError(f"{source}: stream.picture: [x, y, width, height], 4 integers >= 0 (pixels)")
    x, y, pw, ph = (int(v) for v in pic)
    if (pw, ph) != (w, h):
        raise CalibrationError(
            f"{source}: stream.picture: the picture is {pw}x{ph} but the calibration is for {w}x{h}; "
            "its width and height must be the calibration's"
        )
    if x + pw > fw or y + ph > fh:
        raise CalibrationError(
            f"{source}: stream.picture: [{x}, {y}, {pw}, {ph}] does not fit in the {fw}x{fh} frame"
        )
    return StreamLayout(int(fw), int(fh), x, y)


def _fiducial(f: object, source: str) -> Fiducial | None:
    """Validate the optional `fiducial` mapping (see the module docstring)."""
    if f is None:
        return None
    required, optional = {"dictionary", "id", "side_m", "corners"}, {"quiet_zone_m"}
    if not isinstance(f, dict) or not required <= set(f) or set(f) - required - optional:
        raise CalibrationError(
            f"{source}: fiducial: expected keys dictionary, id, side_m, corners[, quiet_zone_m]"
        )
    import cv2  # lazy: the dictionary names are OpenCV's

    name = f["dictionary"]
    ident = getattr(cv2.aruco, name, None) if isinstance(name, str) and name.startswith("DICT_") else None
    if not isinstance(ident, int):
        raise CalibrationError(
            f"{source}: fiducial.dictionary: the name of an OpenCV ArUco dictionary such as DICT_4X4_50 "
            f"required, got {name!r}"
        )
    size = cv2.aruco.getPredefinedDictionary(ident).bytesList.shape[0]
    if not (_count(f["id"]) and f["id"] < size):
        raise CalibrationError(f"{source}: fiducial.id: an integer in 0..{size - 1} ({name}) required")
    if not _positive(f["side_m"]):
        raise CalibrationError(f"{source}: fiducial.side_m: positive number (metres) required")
    corners = f["corners"]
    if not (isinstance(corners, list) and sorted(corners) == list(range(FIDUCIAL_CORNERS))):
        raise CalibrationError(
            f"{source}: fiducial.corners: the ArUco corners 0, 1, 2, 3 in the order of the feature points "
            f"(each once) required, got {corners!r}"
        )
    side = float(f["side_m"])
    quiet = f.get("quiet_zone_m", DEFAULT_QUIET_ZONE * side)
    if not _positive(quiet):
        raise CalibrationError(f"{source}: fiducial.quiet_zone_m: positive number (metres) required")
    c0, c1, c2, c3 = (int(c) for c in corners)
    return Fiducial(name, int(f["id"]), side, (c0, c1, c2, c3), float(quiet))


PATTERN_KINDS = ("chessboard", "charuco", "acircles")


def _positive(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def _pattern(p: object, source: str) -> dict[str, object] | None:
    """Validate the optional `pattern` mapping (see the module docstring)."""
    if p is None:
        return None
    allowed = {"kind", "cols", "rows", "square_m", "marker_m", "dictionary"}
    if not isinstance(p, dict) or set(p) - allowed:
        raise CalibrationError(
            f"{source}: pattern: expected keys kind, cols, rows, square_m[, marker_m, dictionary]"
        )
    if p.get("kind") not in PATTERN_KINDS:
        raise CalibrationError(f"{source}: pattern.kind: one of {', '.join(PATTERN_KINDS)} required")
    for k in ("cols", "rows"):
        if not (isinstance(p.get(k), int) and not isinstance(p.get(k), bool) and p[k] > 0):
            raise CalibrationError(f"{source}: pattern.{k}: positive integer required")
    for k in ("square_m", "marker_m"):
        if (k == "square_m" or k in p) and not _positive(p.get(k)):
            raise CalibrationError(f"{source}: pattern.{k}: positive number (metres) required")
    if "dictionary" in p and not isinstance(p["dictionary"], str):
        raise CalibrationError(f"{source}: pattern.dictionary: a name such as DICT_4X4_50 required")
    return dict(p)


def _views(v: object, source: str) -> tuple[tuple[str, float], ...]:
    """Validate the optional `views` list of {name, error_px}."""
    if v is None:
        return ()
    if not isinstance(v, list):
        raise CalibrationError(f"{source}: views: a list of {{name, error_px}} required")
    out = []
    for j, e in enumerate(v):
        if not (isinstance(e, dict) and set(e) == {"name", "error_px"}):
            raise CalibrationError(f"{source}: views.{j}: expected keys name, error_px")
        err = e["error_px"]
        if not (
            isinstance(err, int | float) and not isinstance(err, bool) and math.isfinite(err) and err >= 0
        ):
            raise CalibrationError(f"{source}: views.{j}.error_px: a finite number >= 0 required")
        out.append((str(e["name"]), float(err)))
    return tuple(out)


def load_calibration(path: str | Path) -> CameraCalibration:
    path = Path(path)
    try:  # the hardened loader of missions (flightstack/config/safe_load.py)
        doc, _ = load_yaml(path, "calibration file")
    except LoadError as exc:
        raise CalibrationError(str(exc)) from None
    return calibration_from_dict(doc, str(path))
