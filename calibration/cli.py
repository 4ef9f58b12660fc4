"""`flightstack calibrate camera | markers | check`: the calibration wizard's command line.

Exit codes: 0 done, 1 verdict failed (degenerate views, RMS too high, markers not found in every
sample), 2 bad input (missing/invalid options, unreadable source, pattern not found, too few views).
No calibration file is written unless the exit code is 0. Results go to stdout, errors and progress
to stderr.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from flightstack.calibration.camera import EXIT_BAD_INPUT, EXIT_OK, EXIT_VERDICT, CaptureOptions, WizardResult
from flightstack.calibration.latency import MAX_SEARCH_S
from flightstack.calibration.patterns import PatternSpec
from flightstack.calibration.prompts import (
    MissingAnswerError,
    answer,
    choice,
    interactive,
    positive_float,
    positive_int,
)
from flightstack.calibration.solve import SolveOptions
from flightstack.calibration.sources import ImageFolderSource, SourceError, TelloSource, VideoFileSource
from flightstack.config.links import PROFILES
from flightstack.vision.camera_file import (
    PATTERN_KINDS,
    CalibrationError,
    CameraCalibration,
    load_calibration,
)


def _error(msg: str, code: int = EXIT_BAD_INPUT) -> int:
    print(f"error: {msg}", file=sys.stderr)
    if code != EXIT_OK:
        print("no calibration file written", file=sys.stderr)
    return code


def _one_line_error(msg: str, code: int = EXIT_BAD_INPUT) -> int:
    """`calibrate latency`'s errors: one line (it writes a links file, never a calibration file)."""
    print(f"error: {msg}", file=sys.stderr)
    return code


def _add_source_options(p: argparse.ArgumentParser, tello: bool) -> None:
    g = p.add_argument_group("source (exactly one)")
    g.add_argument("--images", default=None, help="folder of images (jpg, png, ...)")
    g.add_argument("--video", default=None, help="video file (every --every-th frame)")
    if tello:
        g.add_argument(
            "--tello", default=None, metavar="IP", help="live video of the Tello at IP (no takeoff)"
        )
        g.add_argument("--port", type=int, default=8889, help="Tello command port (default 8889)")
        g.add_argument("--duration", type=float, default=90.0, help="seconds of live capture (default 90)")
        g.add_argument("--rate", type=float, default=5.0, help="live frames analysed per second (default 5)")
        g.add_argument("--downward", action="store_true", help="the Tello EDU's downward camera")
        g.add_argument(
            "--interface",
            default=None,
            metavar="NAME",
            help="the network interface the Tello is reached through (one Wi-Fi adapter per Tello)",
        )
    g.add_argument("--every", type=int, default=1, help="video: use every N-th frame (default 1)")


def _open_source(args: argparse.Namespace) -> ImageFolderSource | VideoFileSource | TelloSource:
    given = [k for k in ("images", "video", "tello") if getattr(args, k, None)]
    if len(given) > 1:
        raise SourceError(f"give one source, not {' and '.join('--' + k for k in given)}")
    if not given:

        def convert(text: str) -> str:
            if not text:
                raise ValueError("a folder, a video file or tello:IP is required")
            return text

        text = answer(
            None,
            "--images DIR, --video FILE or --tello IP",
            "Source: image folder, video file or tello:IP",
            convert,
        )
        if text.startswith("tello:"):
            args.tello = text.split(":", 1)[1]
        elif Path(text).is_dir():
            args.images = text
        else:
            args.video = text
    if getattr(args, "tello", None):
        return TelloSource(args.tello, args.port, args.duration, args.rate, args.downward, args.interface)
    if args.images:
        return ImageFolderSource(args.images)
    return VideoFileSource(args.video, args.every)


def _check_out(out: str) -> Path:
    path = Path(out)
    if path.suffix.lower() not in (".yaml", ".yml", ".json"):
        raise ValueError(f"--out {out}: the file name must end in .yaml, .yml or .json")
    if not path.parent.is_dir():
        raise ValueError(f"--out {out}: folder {path.parent} does not exist")
    return path


def _pattern(args: argparse.Namespace) -> PatternSpec:
    kind = answer(args.pattern, "--pattern", f"Pattern ({'/'.join(PATTERN_KINDS)})", choice(PATTERN_KINDS))
    unit = {"chessboard": "inner corners", "charuco": "squares", "acircles": "circles"}[kind]
    cols = answer(args.cols, "--cols", f"Columns ({unit} per row)", positive_int)
    rows = answer(args.rows, "--rows", f"Rows ({unit} per column)", positive_int)
    what = "circle spacing s (m; centres 2 s apart along a row)" if kind == "acircles" else "square side (m)"
    square = answer(args.square, "--square", what.capitalize(), positive_float)
    marker = None
    if kind == "charuco":
        marker = answer(args.marker_size, "--marker-size", "ArUco marker side (m)", positive_float)
    return PatternSpec(kind, cols, rows, square, marker, args.dictionary)


def _print_result(res: WizardResult) -> None:
    print(f"frames analysed: {res.frames_seen}, views used: {len(res.used)}")
    print(f"rejected views: {len(res.rejected)}")
    for name, reason in res.rejected:
        print(f"  rejected {name}: {reason}")
    if res.used:
        print("per-view reprojection RMS (px):")
        for name, err in res.used:
            print(f"  {name}: {err:.3f}")
    if res.coverage is not None and res.coverage.counts.any():
        grid = res.coverage.grid
        print(
            f"coverage of the image ({grid[0]}x{grid[1]} cells, views per cell): {res.coverage.fraction:.0%}"
        )
        print(res.coverage.render())
        if res.coverage.fraction < 0.5:
            print("  note: less than half of the image is covered; show the board near the edges and corners")


def cmd_camera(args: argparse.Namespace) -> int:
    """The camera wizard: source → views → intrinsics → calibration file."""
    from flightstack.calibration.camera import run_camera_wizard, write_calibration

    try:
        source = _open_source(args)
        spec = _pattern(args)
        out = _check_out(answer(args.out, "--out", "Calibration file to write (.yaml or .json)", str))
        solve = SolveOptions(
            min_views=args.min_views,
            warn_rms_px=args.warn_rms,
            max_rms_px=args.max_rms,
            fix_k3=args.fix_k3,
            outlier_factor=args.outlier_factor,
            min_spread_deg=args.min_spread,
        )
        capture = CaptureOptions(
            max_blur_px=args.max_blur, min_change=args.min_change, max_views=args.max_views
        )
        if solve.min_views < 3:
            raise ValueError("--min-views: at least 3 views are needed")
    except (SourceError, MissingAnswerError, ValueError) as exc:
        return _error(str(exc))
    device = args.device or source.label
    print(f"calibrate camera: {spec.describe()}; source {source.label}; device {device}")
    ignored = getattr(source, "ignored", [])
    if ignored:
        print(f"ignored {len(ignored)} non-image file(s): {', '.join(ignored)}")
    from tqdm import tqdm

    bar = tqdm(
        total=source.total,
        desc="views",
        unit="frame",
        file=sys.stderr,
        disable=True if args.no_progress else None,
        leave=False,
    )

    def on_frame(cap: object) -> None:
        cov = cap.coverage.fraction if cap.coverage is not None else 0.0  # type: ignore[attr-defined]
        bar.set_postfix_str(f"kept {len(cap.views)}, coverage {cov:.0%}")  # type: ignore[attr-defined]
        bar.update(1)

    try:
        res = run_camera_wizard(source, spec, capture, solve, device, on_frame)
    except SourceError as exc:
        return _error(str(exc))
    finally:
        bar.close()
    _print_result(res)
    if res.calibration is None:
        return _error(res.message, res.exit_code)
    cal = res.calibration
    print(
        f"camera matrix: fx {cal.fx:.2f} px, fy {cal.fy:.2f} px, cx {cal.cx:.2f} px, cy {cal.cy:.2f} px "
        f"({cal.width}x{cal.height})"
    )
    print("distortion (k1 k2 p1 p2 k3): " + " ".join(f"{v:.5f}" for v in cal.dist_coeffs))
    print(f"RMS reprojection error: {cal.rms_px:.3f} px")
    print(f"verdict: {res.verdict.upper()}: {res.message}")
    if res.verdict == "warning":
        print(f"warning: {res.message}", file=sys.stderr)
    try:
        notes = write_calibration(cal, out)
    except OSError as exc:
        return _error(f"--out {out}: cannot write: {exc.strerror or exc}")
    for note in notes:
        print(note)
    print(f"written: {out}")
    return EXIT_OK


def _sample_frames(args: argparse.Namespace, limit: int) -> list[tuple[str, np.ndarray]]:
    source = _open_source(args)
    frames: list[tuple[str, np.ndarray]] = []
    for f in source.frames():
        if f.image is None:
            raise SourceError(f"sample {f.name}: {f.error}")
        frames.append((f.name, f.image))
        if len(frames) >= limit:
            break
    return frames


def cmd_markers(args: argparse.Namespace) -> int:
    """Pick the markers' HSV thresholds from regions of sample frames and save them to a calibration; for a
    calibration with a fiducial, write its printable board and check that sample frames show it."""
    from flightstack.calibration.markers import MarkerPickError, Region, pick_markers

    try:
        cal_path = answer(args.calibration, "--calibration", "Calibration file to add the markers to", str)
        base = load_calibration(cal_path)
    except (MissingAnswerError, CalibrationError, ValueError) as exc:
        return _error(str(exc))
    if base.fiducial is not None:
        return _fiducial(args, base)
    if args.board is not None:
        return _error(
            f"--board: {cal_path} declares no fiducial; add a `fiducial:` (docs/calibration.md#the-fiducial)"
        )
    try:
        frames = _sample_frames(args, args.max_samples)
        if not frames:
            raise SourceError("the source delivered no frames")
        texts = list(args.marker or [])
        if not texts and interactive():
            print(
                f"sample frames: {', '.join(n for n, _ in frames[:10])}{' ...' if len(frames) > 10 else ''}"
            )
            while True:
                t = input("Marker as NAME=X,Y,W,H[@FRAME] (pixels; empty when done): ").strip()
                if not t:
                    break
                texts.append(t)
        if not texts:
            raise MissingAnswerError(
                "--marker NAME=X,Y,W,H[@FRAME] is required, once per marker (in feature order)"
            )
        regions = [Region.parse(t) for t in texts]
        out = _check_out(args.out or cal_path)
        for name, img in frames:
            if img.shape[:2] != (base.height, base.width):
                raise ValueError(
                    f"sample {name} is {img.shape[1]}x{img.shape[0]} but {cal_path} is for "
                    f"{base.width}x{base.height}"
                )
        res = pick_markers(base, frames, regions)
    except (SourceError, MissingAnswerError, CalibrationError, MarkerPickError, ValueError) as exc:
        return _error(str(exc))
    print(f"calibrate markers: {len(regions)} marker(s) on {len(frames)} sample frame(s)")
    failed = [(n, r) for n, r in res.per_frame if r is not None]
    if res.markers is None:
        for n, r in failed:
            print(f"  {n}: {r}")
        return _error(res.message, EXIT_VERDICT)
    for mk in res.markers:
        print(f"  {mk.name}: hsv_lo {list(mk.hsv_lo)}, hsv_hi {list(mk.hsv_hi)}, rgb {list(mk.rgb or ())}")
    print(f"verified: {res.message}")

    new = CameraCalibration(**{**base.__dict__, "markers": res.markers})
    try:
        new.save(out)
    except OSError as exc:
        return _error(f"--out {out}: cannot write: {exc.strerror or exc}")
    print(f"written: {out}")
    return EXIT_OK


def _fiducial(args: argparse.Namespace, cal: CameraCalibration) -> int:
    """`calibrate markers` for a calibration with a fiducial: --board writes the printable board; a source
    (--images, --video) is checked: every sample, cut to the calibrated picture, must show the marker."""
    from flightstack.calibration.board import write_board
    from flightstack.vision.detect import detect_markers
    from flightstack.vision.picture import picture

    fid = cal.fiducial
    assert fid is not None
    if args.marker:
        return _error(
            "--marker picks colour markers; this calibration declares a fiducial (use --board, --images)"
        )
    has_source = bool(args.images or args.video or args.tello)
    if args.board is None and not has_source:
        return _error(
            "a fiducial's calibration needs --board FILE (.png, .pdf) and/or --images DIR, --video FILE "
            "or --tello IP"
        )
    print(
        f"calibrate markers: fiducial ArUco {fid.dictionary} id {fid.id}, side {fid.side_m:g} m, quiet zone "
        f"{fid.quiet_zone_m:g} m, corners {list(fid.corners)}"
    )
    if args.board is not None:
        try:
            w, h = write_board(fid, args.board, args.dpi)
        except (OSError, ValueError) as exc:
            return _error(f"--board {args.board}: {exc}")
        print(
            f"board written: {args.board} ({w}x{h} px at {args.dpi:g} dpi; print at 100 %, check its 100 mm "
            "scale bar)"
        )
    if not has_source:
        return EXIT_OK
    try:
        frames = _sample_frames(args, args.max_samples)
        if not frames:
            raise SourceError("the source delivered no frames")
        found = []
        for name, img in frames:
            pic = picture(img, cal)
            if pic.shape[:2] != (cal.height, cal.width):
                raise ValueError(
                    f"sample {name} is {img.shape[1]}x{img.shape[0]} but the calibration is for "
                    f"{cal.width}x{cal.height}"
                    + ("" if cal.stream is None else f" in {cal.stream.width}x{cal.stream.height}")
                )
            found.append((name, detect_markers(pic, cal)))
    except (SourceError, ValueError) as exc:
        return _error(str(exc))
    for name, det in found:
        if det.ok and det.pixels is not None:
            corners = " ".join(f"({u:.1f}, {v:.1f})" for u, v in det.pixels)
            print(f"  {name}: found, feature points at {corners} px")
        else:
            print(f"  {name}: {det.reason}")
    n_ok = sum(det.ok for _, det in found)
    if n_ok < len(found):
        print(f"error: the fiducial was found in {n_ok} of {len(found)} samples", file=sys.stderr)
        return EXIT_VERDICT
    print(f"verified: the fiducial found in all {len(found)} samples")
    return EXIT_OK


def cmd_check(args: argparse.Namespace) -> int:
    """Load a calibration and report the undistortion of a sample image."""
    from flightstack.calibration.check import check_calibration

    try:
        cal = load_calibration(args.calibration)
        bgr = cv2.imread(args.image, cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"--image {args.image}: cannot read it as an image")
        spec = None
        if args.pattern:
            if args.cols is None or args.rows is None or args.square is None:
                raise ValueError("--pattern needs --cols, --rows and --square")
            spec = PatternSpec(
                args.pattern, args.cols, args.rows, args.square, args.marker_size, args.dictionary
            )
        rep = check_calibration(cal, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), spec)
    except (CalibrationError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    rms = "n/a" if cal.rms_px is None else f"{cal.rms_px:.3f} px"
    print(f"calibration {args.calibration}: device {cal.device or '?'}, {cal.width}x{cal.height}, RMS {rms}")
    print(f"fx {cal.fx:.2f} px, fy {cal.fy:.2f} px, cx {cal.cx:.2f} px, cy {cal.cy:.2f} px")
    for line in rep.lines():
        print(line)
    if args.out:
        if not cv2.imwrite(args.out, cv2.cvtColor(rep.undistorted, cv2.COLOR_RGB2BGR)):
            print(f"error: --out {args.out}: cannot write the undistorted image", file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f"undistorted sample written: {args.out}")
    if spec is not None and rep.pattern_rms_px is None:
        return EXIT_VERDICT
    if rep.pattern_rms_px is not None and rep.pattern_rms_px > args.max_rms:
        print(f"verdict: FAILED: the sample's reprojection RMS exceeds {args.max_rms:g} px", file=sys.stderr)
        return EXIT_VERDICT
    return EXIT_OK


def _add_pattern_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pattern", choices=PATTERN_KINDS, default=None, help="calibration target")
    p.add_argument(
        "--cols", type=int, default=None, help="inner corners (chessboard) / squares / circles per row"
    )
    p.add_argument("--rows", type=int, default=None, help="the same per column")
    p.add_argument("--square", type=float, default=None, help="square side, or circle spacing s (metres)")
    p.add_argument("--marker-size", type=float, default=None, help="ChArUco: the ArUco marker side (metres)")
    p.add_argument(
        "--dictionary", default="DICT_4X4_50", help="ChArUco ArUco dictionary (default DICT_4X4_50)"
    )


MIN_CORRELATION = 0.8
"""Below this cross-correlation of the frames' markers with the predicted ones, the video's latency is not
trusted (the markers were mostly lost, or the session's calibration or mount is wrong)."""


def cmd_latency(args: argparse.Namespace) -> int:
    """Estimate the video and rc latencies of a recorded session (--session) or of a calibration flight
    flown now on a rig (--rig); print and write the links file."""
    from flightstack.calibration.latency_session import load_session

    if (args.session is None) == (args.rig is None):
        return _one_line_error("give either --session FILE (a recorded session) or --rig RIG (fly one now)")
    if args.rig is not None:
        return _fly_latency(args)
    try:
        if args.out:
            _check_links_out(args.out)
        video, rc = load_session(args.session)
    except (OSError, ValueError) as exc:
        text = str(exc)
        return _one_line_error(text if text.startswith("--out") else f"session {args.session}: {text}")
    if video is None and rc is None:
        return _one_line_error(f"session {args.session}: neither a video nor an rc part")
    if video is not None:
        try:
            load_calibration(video.calibration)
        except (OSError, ValueError) as exc:
            return _one_line_error(f"session {args.session}: its calibration {video.calibration}: {exc}")
    return _estimate_latency(args, video, rc, f"session {Path(args.session).name}")


def _session_path(args: argparse.Namespace) -> Path:
    """Where a flown session is saved: beside --out (FILE.session.npz), else latency_session_<UTC>.npz."""
    import datetime

    if args.out:
        out = Path(args.out)
        return out.with_name(out.stem + ".session.npz")
    return Path(f"latency_session_{datetime.datetime.now(datetime.UTC):%Y%m%dT%H%M%SZ}.npz")


def _fly_latency(args: argparse.Namespace) -> int:
    """`--rig`: fly the calibration (calibration.latency_flight), save the session, estimate, write."""
    from flightstack.calibration.latency_flight import (
        CalibrationFlightError,
        fly_latency_calibration,
        one_drone,
    )
    from flightstack.calibration.latency_session import save_session
    from flightstack.config.mission import MissionError, load_mission
    from flightstack.config.rig import RigError

    overrides: dict[str, object] = {} if args.links is None else {"links": {"profile": args.links}}
    try:
        mission = load_mission(args.experiment, overrides, rig=args.rig)
        one = one_drone(mission, args.drone)
        if args.out:
            _check_links_out(args.out)
    except (MissionError, RigError, ValueError, OSError) as exc:
        return _one_line_error(str(exc))
    drone = one.drones[0].id
    if mission.rig_type.flies_real_drones:
        code = _preflight_and_confirm(one, drone, args.yes)
        if code:
            return code
    session = _session_path(args)
    say = lambda line: print(line, file=sys.stderr)  # noqa: E731
    say(f"calibrate latency: drone {drone} on rig {mission.rig} ({mission.backend}); session -> {session}")
    try:
        video, rc, flown_s, wall_s = fly_latency_calibration(mission, args.drone, say=say)
    except KeyboardInterrupt:
        print("interrupted: landed; nothing written", file=sys.stderr)
        return 130
    except CalibrationFlightError as exc:
        return _one_line_error(f"{exc}; landed, nothing written", EXIT_VERDICT)
    except Exception as exc:  # an abort, the safety layer, a device: the drone has landed (Flight)
        why = f"{type(exc).__name__}: {exc}"
        return _one_line_error(f"the calibration flight failed: {why}; landed", EXIT_VERDICT)
    print(
        f"flown: {flown_s:.1f} s from takeoff's end to the last step (the rig's clock); {wall_s:.1f} s "
        "of wall clock in all (with the lab's start, takeoff and landing)"
    )
    try:
        save_session(session, video=video, rc=rc)
    except OSError as exc:
        return _one_line_error(f"session {session}: cannot write: {exc.strerror or exc}", EXIT_VERDICT)
    print(f"session written: {session} (`flightstack calibrate latency --session {session}` re-estimates)")
    return _estimate_latency(
        args, video, rc, f"flown on rig {mission.rig}, drone {drone}; session {session.name}"
    )


def _check_links_out(out: str) -> None:
    path = Path(out)
    if path.suffix.lower() not in (".yaml", ".yml"):
        raise ValueError(f"--out {out}: a links file ends in .yaml or .yml")
    if not path.parent.is_dir():
        raise ValueError(f"--out {out}: folder {path.parent} does not exist")


def _preflight_and_confirm(mission: object, drone: int, yes: bool) -> int:
    """Real drones: preflight the calibrated drone's devices, then ask; 0 to go on, else the exit code."""
    from flightstack.runtime.rig import rig_of

    report = rig_of(mission).preflight(mission, [drone])  # type: ignore[arg-type]
    if report is not None:
        print(report.table)
    if report is not None and not report.passed:
        return _one_line_error("preflight failed; nothing took off", EXIT_VERDICT)
    question = f"Drone {drone} will take off, yaw over the still target for about 30 s and land. Area clear?"
    if yes:
        return EXIT_OK
    if not interactive():
        return _one_line_error("this flies a real drone; pass --yes to confirm")
    if input(f"{question} [y/N] ").strip().lower() not in ("y", "yes"):
        print("aborted", file=sys.stderr)
        return EXIT_VERDICT
    return EXIT_OK


def _estimate_latency(args: argparse.Namespace, video: object, rc: object, how: str) -> int:
    """Estimate both parts (either may be None), print them, write the links file (--out)."""
    from flightstack.calibration.latency import DelayEstimate, ResponseEstimate
    from flightstack.calibration.latency_report import links_text, write_links_file
    from flightstack.calibration.latency_session import RcRecord, VideoRecord

    assert video is None or isinstance(video, VideoRecord)
    assert rc is None or isinstance(rc, RcRecord)
    v_est: DelayEstimate | None = None
    r_est: ResponseEstimate | None = None
    try:
        if video is not None:
            v_est = video.estimate(args.max_lag, args.window)
            print(
                f"video: capture -> decoded {1e3 * v_est.mean_s:.1f} ms mean, {1e3 * v_est.sd_s:.1f} ms sd "
                f"(5-95 %: {1e3 * v_est.p5_s:.0f}-{1e3 * v_est.p95_s:.0f} ms; pixel noise "
                f"{1e3 * v_est.noise_s:.1f} ms); {v_est.n_used} of {v_est.n_frames} frames timed; "
                f"correlation {v_est.correlation:.3f}"
            )
        if rc is not None:
            r_est = rc.estimate(args.max_rc_lag)
            print(
                f"rc: sent -> motion starts {1e3 * r_est.mean_s:.1f} ms mean, {1e3 * r_est.sd_s:.1f} ms sd "
                f"over {r_est.n_steps} changes; then a {1e3 * r_est.tau_s:.0f} ms lag, gain {r_est.gain:.4g}"
            )
    except (OSError, ValueError) as exc:
        return _one_line_error(f"{how}: {exc}", EXIT_VERDICT)
    if v_est is not None and v_est.correlation < MIN_CORRELATION:
        return _one_line_error(
            f"the markers follow the predicted ones poorly (correlation {v_est.correlation:.2f} < "
            f"{MIN_CORRELATION}): check the calibration, the mount and that the markers stayed in view",
            EXIT_VERDICT,
        )
    text = links_text(v_est, r_est, how=how)
    print(text, end="")
    if args.out:
        try:
            write_links_file(args.out, text)
        except OSError as exc:
            return _one_line_error(f"--out {args.out}: cannot write: {exc.strerror or exc}", EXIT_VERDICT)
        print(f"written to {args.out}; include it in the rig with `links: {{include: {args.out}}}`")
    return EXIT_OK


def _search_s(text: str) -> float:
    """argparse type of --max-lag, --max-rc-lag and --window (calibration.latency.check_search)."""
    from flightstack.calibration.latency import check_search

    try:
        return check_search("the value", float(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc}") from None


_UP_TO = f"at most {MAX_SEARCH_S:g} s"


def register(cal_sub: argparse._SubParsersAction) -> None:
    """Add `camera`, `markers`, `check` and `latency` to the `flightstack calibrate` subcommands."""
    c = cal_sub.add_parser(
        "camera",
        help="camera intrinsics and distortion from pattern views (chessboard, ChArUco, circle grid)",
        description="Calibrate a camera. Missing options are asked for at a terminal; in scripts pass all.",
    )
    _add_source_options(c, tello=True)
    _add_pattern_options(c)
    c.add_argument("--out", default=None, help="calibration file to write (.yaml, or .json)")
    c.add_argument("--device", default=None, help="device id stored in the file (default: the source's name)")
    c.add_argument("--max-views", type=int, default=40, help="stop after this many kept views (default 40)")
    c.add_argument("--min-views", type=int, default=6, help="refuse to calibrate from fewer (default 6)")
    c.add_argument("--max-blur", type=float, default=5.0, help="largest edge width accepted, px (default 5)")
    c.add_argument(
        "--min-change",
        type=float,
        default=0.015,
        help="a view must move the board by this fraction of the image diagonal (default 0.015)",
    )
    c.add_argument("--outlier-factor", type=float, default=3.0, help="drop views above this x median error")
    c.add_argument(
        "--min-spread",
        type=float,
        default=10.0,
        help="refuse if all board normals lie within this angle (deg)",
    )
    c.add_argument("--warn-rms", type=float, default=1.0, help="warn above this RMS, px (default 1)")
    c.add_argument("--max-rms", type=float, default=3.0, help="refuse above this RMS, px (default 3)")
    c.add_argument("--fix-k3", action="store_true", help="fit k1, k2, p1, p2 only (k3 = 0)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_camera)

    m = cal_sub.add_parser(
        "markers",
        help="the target's markers: colour thresholds from sample frames, or a fiducial's board and check",
        description="Pick marker thresholds from pixel boxes X,Y,W,H in sample frame FRAME (default 0). "
        "For a calibration that declares a fiducial: --board writes it to print, --images/--video check "
        "that every sample shows it.",
    )
    m.add_argument("--calibration", default=None, help="camera calibration file to add the markers to")
    _add_source_options(m, tello=True)
    m.add_argument(
        "--marker",
        action="append",
        default=None,
        metavar="NAME=X,Y,W,H[@FRAME]",
        help="one per marker, in the order of the target's feature points",
    )
    m.add_argument("--max-samples", type=int, default=50, help="use at most this many sample frames")
    m.add_argument("--out", default=None, help="file to write (default: overwrite --calibration)")
    m.add_argument(
        "--board",
        default=None,
        metavar="FILE",
        help="a fiducial's calibration: write its printable board (.png or .pdf) at its true size",
    )
    m.add_argument(
        "--dpi", type=float, default=300.0, help="the board's resolution, dots per inch (default 300)"
    )
    m.set_defaults(func=cmd_markers)

    k = cal_sub.add_parser("check", help="load a calibration and report the undistortion of a sample image")
    k.add_argument("calibration", help="calibration file (.yaml or .json)")
    k.add_argument("--image", required=True, help="sample image of the calibrated size")
    k.add_argument("--out", default=None, help="write the undistorted sample here (png, jpg)")
    _add_pattern_options(k)
    k.add_argument("--max-rms", type=float, default=1.0, help="fail if the sample's pattern RMS exceeds this")
    k.set_defaults(func=cmd_check)

    lat = cal_sub.add_parser(
        "latency",
        help="the camera's capture -> decoded latency and rc -> motion: fly it on a rig, or from a session",
        description="Measure a lab's video and rc latencies and write the links file a rig includes with "
        "`links: {include: FILE}` (docs/calibration.md). --rig RIG flies the calibration now: one drone "
        "with a downward camera takes off, hovers over the still target, yaws in a known pattern, flies "
        "yaw-rate steps and lands; the session is saved beside --out. --session FILE re-estimates a "
        "recorded session (.npz: motion-capture poses, decoded frames' markers, rc commands).",
    )
    src = lat.add_mutually_exclusive_group()
    src.add_argument(
        "--rig", default=None, help="fly the calibration on this rig (a lab file, emulated-lab, lab-sim)"
    )
    src.add_argument("--session", default=None, help="recorded session (.npz) to estimate")
    lat.add_argument(
        "--experiment",
        default="paper_experiment",
        help="experiment that names the drones, their cameras and the target's markers (default "
        "paper_experiment)",
    )
    lat.add_argument(
        "--drone", type=int, default=None, help="drone id (default: the first with a downward camera)"
    )
    lat.add_argument(
        "--links",
        default=None,
        choices=sorted(PROFILES),
        help="replace the rig's links with a profile (emulated and simulated labs: the links they emulate)",
    )
    lat.add_argument("--yes", action="store_true", help="confirm that a real drone may take off")
    lat.add_argument("--out", default=None, help="links file to write (.yaml); default: print only")
    lat.add_argument(
        "--max-lag", type=_search_s, default=1.0, help=f"largest latency looked for, s (default 1; {_UP_TO})"
    )
    lat.add_argument(
        "--max-rc-lag", type=_search_s, default=0.5, help=f"largest rc latency looked for, s (0.5; {_UP_TO})"
    )
    lat.add_argument(
        "--window",
        type=_search_s,
        default=0.3,
        help=f"each frame is timed within the peak ± this, s (default 0.3; {_UP_TO})",
    )
    lat.set_defaults(func=cmd_latency)
