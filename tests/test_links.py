"""The rig's links on the simulated lab: frames rendered at their capture time arrive late and are
stamped when taken; the `tello` profile is seeded (the same run twice is the same run); `perfect` is
what the lab did before links were modelled (tests/fingerprints.py holds that bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest

from flightstack.config.links import LINKS, PROFILES, LinkSpec, LinksSpec
from flightstack.config.mission import MissionError, load_mission
from flightstack.recording.timeseries import ARRAY_FIELDS, MACHINE_FIELDS
from tests.conftest import fly_mode


def _lab(links: dict[str, object], seconds: float = 2.0):
    return load_mission(
        "paper_experiment", {"duration_s": seconds, "compare_modes": ["none"], "links": links}, rig="lab-sim"
    )


def test_a_late_camera_shows_frames_as_old_as_its_latency_and_stamped_when_taken() -> None:
    """Frames taken at k/30 s arriving 0.2 s later: at tick t the newest one arrived was taken in
    (t − 0.2 − 1/30, t − 0.2], so every frame age is in [0.2, 0.2 + 1/30] s."""
    rec = fly_mode(_lab({"profile": "perfect", "video": {"latency_s": 0.2, "rate_hz": 30.0}}), "none")
    age = rec.frame_age[: rec.ticks_done]
    seen = age[np.isfinite(age)]
    assert seen.size > 0.8 * age.size
    assert seen.min() >= 0.2 - 1e-9 and seen.max() <= 0.2 + 1 / 30 + 1e-9, (seen.min(), seen.max())
    now = fly_mode(_lab({"profile": "perfect"}), "none").frame_age
    assert np.nanmax(now) == 0.0  # the present, as before


def test_the_tello_profile_is_seeded_and_worse_than_perfect() -> None:
    a = fly_mode(_lab({"profile": "tello"}), "none")
    b = fly_mode(_lab({"profile": "tello"}), "none")
    for f in ARRAY_FIELDS:
        if f not in MACHINE_FIELDS:
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    age = a.frame_age[: a.ticks_done]
    assert np.nanmedian(age) >= PROFILES["tello"]["video"].latency_s


def test_a_link_named_in_the_rig_replaces_the_profiles_and_bad_values_are_refused() -> None:
    spec = LinksSpec(profile="tello", rc=LinkSpec(latency_s=0.2))
    assert spec.link("rc").latency_s == 0.2 and spec.link("video") == PROFILES["tello"]["video"]
    assert LinksSpec().link("rc") == PROFILES["perfect"]["rc"] and LinksSpec().link("video").perfect
    assert set(LINKS) >= {name for table in PROFILES.values() for name in table}
    for bad in ({"profile": "wifi"}, {"video": {"loss": 1.0}}, {"rc": {"latency_s": -0.1}}):
        with pytest.raises(MissionError, match="links"):
            _lab(bad)


def test_the_emulated_lab_counts_a_frame_stale_only_past_its_video_links_longest_delay() -> None:
    """The emulated lab's hardware.max_frame_age_s: the lab's default (chosen on loopback) after the
    longest delay the video link its emulators apply gives a frame (docs/links.md asks a real lab the
    same)."""
    from flightstack.config.hardware import HardwareSpec
    from flightstack.sim_backend.emulated_lab import max_frame_age_s
    from flightstack.sim_backend.emulators.device_links import emulated_links

    def bound(links: dict[str, object]) -> float:
        return max_frame_age_s(emulated_links(LinksSpec.model_validate(links)).get("video"))

    default = HardwareSpec.model_fields["max_frame_age_s"].default
    tello = PROFILES["tello"]["video"]
    assert max_frame_age_s(None) == bound({}) == bound({"profile": "perfect"}) == default
    assert bound({"profile": "tello"}) == pytest.approx(default + tello.latency_s + tello.jitter_s)
    written = {"profile": "tello", "video": {"latency_s": 0.2, "jitter_s": 0.05, "rate_hz": 30.0}}
    assert bound(written) == pytest.approx(default + 0.25)
