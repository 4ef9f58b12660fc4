"""The rig's links (`links:`): how late, how often and how reliably each kind of data reaches the flight.

A link is one direction of one kind of data: each drone's `video` (camera → computer), `state`
(telemetry → computer) and `rc` (computer → drone), `mocap` (motion capture → computer), `robot`
(computer → ground robot) and the `bus` (between agent processes). A `LinkSpec` gives its fixed latency
and jitter (s: each sample is late by latency_s + U(0, jitter_s)), its rate (samples per second; None:
as often as the source produces them) and the probability that a sample is lost. The `video` link loses
datagrams too (`datagram_loss`, in bursts of `datagram_burst`): a real Tello's frame is about nine
datagrams, and losing one damages a frame rather than removing it (docs/links.md).

`profile` names a table of links; a link written out in the section replaces that link of the profile:

- `perfect`: what the simulated lab did before links were modelled, kept so that its recordings do not
  change: commands take effect 50 ms after they are sent, everything else arrives at once;
- `tello`: a Tello on Wi-Fi and motion capture on a wired network, from users' measurements
  (docs/links.md lists each number with its source).

`LinkDelays` draws what a link does to each sample (its delay, whether it is lost) from a seeded generator:
the simulated lab applies links with it (sim_backend/lab.py), and so do the emulated lab's device links
(sim_backend/emulators/device_links.py); which links each rig applies is in docs/links.md.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from flightstack.config.types import MAX_TIME_S
from flightstack.config.types import Strict as _Strict
from flightstack.netem import LINKS
from flightstack.netem import PROFILES as NETWORK_PROFILES

Delay = Annotated[float, Field(ge=0, le=MAX_TIME_S, allow_inf_nan=False)]


class LinkSpec(_Strict):
    """One link: latency_s + U(0, jitter_s) late (s); rate_hz samples per second (None: every sample
    the source makes); loss: probability that a sample never arrives. `video` only: datagram_loss, the
    long-run fraction of a frame's datagrams lost, in bursts of datagram_burst datagrams on average (the
    simple Gilbert model, flightstack.netem.LinkProfile.bursty, one step per datagram)."""

    latency_s: Delay = 0.0
    jitter_s: Delay = 0.0
    rate_hz: Annotated[float, Field(gt=0, le=10000, allow_inf_nan=False)] | None = None
    loss: Annotated[float, Field(ge=0, lt=1)] = 0.0
    datagram_loss: Annotated[float, Field(ge=0, lt=1)] = 0.0
    datagram_burst: Annotated[float, Field(ge=1, le=1000, allow_inf_nan=False)] = 1.0

    @property
    def perfect(self) -> bool:
        """Nothing late, nothing lost, nothing resampled."""
        return (
            self.latency_s == 0
            and self.jitter_s == 0
            and self.rate_hz is None
            and self.loss == 0
            and self.datagram_loss == 0
        )


NONE = LinkSpec()

PROFILES: dict[str, dict[str, LinkSpec]] = {
    "perfect": {"rc": LinkSpec(latency_s=0.05)},
    "tello": {
        # the Tello's H.264 stream: 300-800 ms through the usual readers (DJITelloPy #77), ~1 s with
        # OpenCV's buffered capture (DJITelloPy #87); 30 fps (Tello SDK 2.0); datagrams lost now and then
        # (TelloPy #20, #76), not whole frames: 0.2 % in bursts of 3 is assumed (docs/links.md)
        "video": LinkSpec(latency_s=0.3, jitter_s=0.1, rate_hz=30.0, datagram_loss=0.002, datagram_burst=3.0),
        # the state string at about 10 Hz (Tello SDK 2.0 user guide), one Wi-Fi hop
        "state": LinkSpec(latency_s=0.02, jitter_s=0.02, rate_hz=10.0, loss=0.02),
        # an rc datagram over Wi-Fi, then the flight controller's response (the lab's 50 ms plus jitter)
        "rc": LinkSpec(latency_s=0.05, jitter_s=0.03, loss=0.02),
        # OptiTrack/Motive over wired Ethernet: a few ms of system latency (NatNet reports it per frame)
        "mocap": LinkSpec(latency_s=0.005, jitter_s=0.002),
        "robot": LinkSpec(latency_s=0.02, jitter_s=0.01),
    },
}
"""Profile name -> its links (a link not named is NONE)."""


class LinksSpec(_Strict):
    """The `links:` section: the radio's profile (`network`), a table of links (`profile`) and links
    that replace the table's."""

    network: str = "clean"
    """The radio under the links (flightstack.netem.PROFILES): every packet the emulated lab's devices send
    or receive passes it after its link (docs/links.md, "The radio")."""
    profile: Literal["perfect", "tello"] = "perfect"
    video: LinkSpec | None = None
    state: LinkSpec | None = None
    rc: LinkSpec | None = None
    mocap: LinkSpec | None = None
    robot: LinkSpec | None = None
    bus: LinkSpec | None = None

    @field_validator("network")
    @classmethod
    def _known_network(cls, v: str) -> str:
        if v not in NETWORK_PROFILES:
            raise ValueError(f"unknown network profile {v!r}; valid: {', '.join(NETWORK_PROFILES)}")
        return v

    @model_validator(mode="after")
    def _datagrams_on_video_only(self) -> LinksSpec:
        for name in LINKS:
            own: LinkSpec | None = getattr(self, name)
            if name != "video" and own is not None and own.datagram_loss > 0:
                raise ValueError(
                    f"{name}.datagram_loss: only the video link is sent in datagrams that a loss can damage "
                    "(a frame of several); use `loss` for the other links"
                )
        return self

    def link(self, name: str) -> LinkSpec:
        """The link `name` (one of LINKS): the section's own, else the profile's, else NONE."""
        if name not in LINKS:
            raise ValueError(f"unknown link {name!r}; known: {', '.join(LINKS)}")
        own: LinkSpec | None = getattr(self, name)
        return own if own is not None else PROFILES[self.profile].get(name, NONE)

    def emulated(self, name: str) -> LinkSpec:
        """The link `name` as the emulated lab applies it: profile `perfect` changes nothing there (its
        devices have their own delays, e.g. the emulated Tello's response), links written out do."""
        own: LinkSpec | None = getattr(self, name)
        return own if own is not None else (NONE if self.profile == "perfect" else self.link(name))


def network_in_links(data: dict[str, Any], source: str) -> dict[str, Any]:
    """`data` with a top-level `network: PROFILE` (the key before the radio joined `links:`) moved to
    `links.network`, saying so in one line; both at once is a ValueError naming them."""
    if "network" not in data:
        return data
    out = dict(data)
    value = out.pop("network")
    links = out.get("links")
    links = {} if links is None else links
    if isinstance(links, dict):  # (anything else: the schema names `links`)
        if "network" in links:
            raise ValueError(f"{source}: network: and links.network: both given; keep links.network only")
        out["links"] = {**links, "network": value}
    logging.getLogger(__name__).warning("%s: `network:` is now `links.network:` (docs/links.md)", source)
    return out


class LinkDelays:
    """One link's samples (flightstack.config.links.LinkSpec): each arrives latency_s + U(0, jitter_s)
    late (s) and is lost with probability `loss`. Draws from `rng` only for jitter and loss, so a link
    without them draws nothing (the recordings of a rig without them do not change)."""

    def __init__(self, spec: LinkSpec, rng: np.random.Generator | None = None) -> None:
        if (spec.jitter_s > 0 or spec.loss > 0) and rng is None:
            raise ValueError("a link with jitter or loss needs a generator")
        self.spec, self.rng = spec, rng
        self.lost_count = 0

    def delay(self) -> float:
        """How late the next sample arrives (s)."""
        s = self.spec
        jitter = float(self.rng.uniform(0.0, s.jitter_s)) if s.jitter_s > 0 and self.rng else 0.0
        return s.latency_s + jitter

    def lost(self) -> bool:
        """Whether the next sample is lost (counted)."""
        gone = self.spec.loss > 0 and self.rng is not None and bool(self.rng.random() < self.spec.loss)
        self.lost_count += gone
        return gone
