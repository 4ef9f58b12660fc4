"""The measured links as a file a rig includes (`links: {include: FILE}`, flightstack.config.rig): the
`links:` it applies (latency_s, jitter_s: a link `latency_s + U(0, jitter_s)` with the measured mean and
standard deviation) and `measured:` how they were found (date, mean, spread, percentiles, frames), which
the rig does not apply. Writing a file of its own keeps the rig's comments as they are.
"""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any

import yaml

from flightstack.calibration.latency import DelayEstimate, ResponseEstimate


def _ms(x: float) -> float:
    """Seconds rounded to a tenth of a millisecond (what a measurement of this kind resolves)."""
    return round(float(x), 4)


def video_entry(est: DelayEstimate) -> tuple[dict[str, float], dict[str, Any]]:
    """(the `video` link, its `measured` record) of a camera's estimate."""
    latency, jitter = est.as_link()
    measured = {
        "mean_s": _ms(est.mean_s), "sd_s": _ms(est.sd_s), "p5_s": _ms(est.p5_s), "p95_s": _ms(est.p95_s),
        "noise_s": _ms(est.noise_s), "correlation": round(est.correlation, 4), "frames_timed": est.n_used,
        "frames": est.n_frames,
    }  # fmt: skip
    return {"latency_s": _ms(latency), "jitter_s": _ms(jitter)}, measured


def rc_entry(est: ResponseEstimate) -> tuple[dict[str, float], dict[str, Any]]:
    """(the `rc` link, its `measured` record) of an rc → motion estimate: the link is the delay until the
    motion starts; the response after it (tau_s, gain) is recorded, not applied."""
    latency, jitter = est.as_link()
    measured = {
        "mean_s": _ms(est.mean_s), "sd_s": _ms(est.sd_s), "tau_s": _ms(est.tau_s),
        "gain": round(est.gain, 5), "changes_timed": est.n_steps,
    }  # fmt: skip
    return {"latency_s": _ms(latency), "jitter_s": _ms(jitter)}, measured


def links_text(
    video: DelayEstimate | None = None,
    rc: ResponseEstimate | None = None,
    when: datetime.datetime | None = None,
    how: str = "",
) -> str:
    """The links file's text (YAML with a header that says how to include it)."""
    when = when or datetime.datetime.now(datetime.UTC)
    links: dict[str, Any] = {}
    measured: dict[str, Any] = {"date": when.strftime("%Y-%m-%dT%H:%M:%SZ")}
    if how:
        measured["how"] = how
    for name, entry in (("video", video and video_entry(video)), ("rc", rc and rc_entry(rc))):
        if entry:
            links[name], measured[name] = entry
    if not links:
        raise ValueError("nothing measured: give a video or an rc estimate")
    head = (
        f"# A lab's links as measured by `flightstack calibrate latency` on {measured['date']}.\n"
        "# Include it in the rig: `links: {include: THIS_FILE}` (relative to the rig's directory); a link\n"
        "# the rig writes out beside `include` wins. Each link is latency_s + U(0, jitter_s), with the\n"
        "# measured mean and standard deviation; `measured:` is for the reader (docs/links.md). For the\n"
        "# rig's `compensation:`, response_s is measured.rc.tau_s (command_delay_s follows the rc link).\n"
    )
    body = yaml.safe_dump({"links": links, "measured": measured}, sort_keys=False, default_flow_style=None)
    return head + body


def write_links_file(path: str | Path, text: str) -> Path:
    """Write the links file (its directory must exist); returns its path."""
    p = Path(path)
    p.write_text(text, encoding="utf-8")
    return p


__all__ = ["links_text", "rc_entry", "video_entry", "write_links_file"]
