"""The packet decisions of the link models, pinned per seed: a change to how links are described, named or
wrapped must leave every sample's and datagram's fate as it was (or re-fly the network tables, saying why).

Each digest is the SHA-256 of the decisions (due times rounded to 1 ns, None or [] for lost) of a fixed
sequence of arrival times, for seeds 0-2, on every link of every profile the repository ships: the
`links:` profiles through the emulated lab's stages, the `network:` profiles through the radio's models.
"""

from __future__ import annotations

import hashlib

import numpy as np

from flightstack.config.links import PROFILES as LINK_PROFILES
from flightstack.config.links import LinksSpec
from flightstack.netem import PROFILES as NETWORK_PROFILES
from flightstack.netem import LinkModel, StreamModel, blackout_windows
from flightstack.sim_backend.emulators.device_links import DeviceLinks, emulated_links
from flightstack.sim_backend.emulators.radio import DeviceRadio

SEEDS = (0, 1, 2)
TIMES = np.cumsum(np.random.default_rng(7).exponential(0.01, 400)).tolist()
"""Arrival times (s): a packet every 10 ms on average, 4 s in all (past the outage profile's first blackout
at 12 s only through the epoch below)."""
EPOCH = -10.0
"""The radios' epoch: their blackout windows count from it, so the outage profile's first one (12 s after
the epoch) falls inside TIMES."""
RADIO_LINKS = {
    "tello1": {"command": "rc", "reply": "rc", "state": "state", "video": "video"},
    "natnet": {"frames": "mocap"},
    "rover": {"uplink": "robot", "downlink": "robot"},
}
"""The emulated lab's radios: device -> link -> the kind of link it is (sim_backend/emulated_lab.py)."""


def _digest(rows: list[object]) -> str:
    def norm(v: object) -> object:
        if isinstance(v, float):
            return round(v, 9)
        if isinstance(v, list | tuple):
            return [norm(x) for x in v]
        return v

    return hashlib.sha256(repr([norm(r) for r in rows]).encode()).hexdigest()[:16]


def links_decisions() -> str:
    """Every applied `links:` link of both profiles (the tello profile's, and perfect's rc written out),
    through DeviceLinks: each sample's due time, and the video datagrams' keep/lose."""
    rows: list[object] = []
    for profile in sorted(LINK_PROFILES):
        spec = LinksSpec(profile=profile)
        specs = emulated_links(spec) or {"rc": spec.link("rc")}
        for seed in SEEDS:
            for device in (0, 1, 2):
                dl = DeviceLinks(specs, seed, device, f"pin{device}")
                for name in sorted(specs):
                    rows.append([profile, seed, device, name, [dl.decide(name, t) for t in TIMES]])
                    rows.append([name, [dl.keeps(name, t, 1460) for t in TIMES]])
                dl.close()
    return _digest(rows)


def network_decisions() -> str:
    """Every radio link of every `network:` profile, through DeviceRadio (blackouts from the epoch), and
    the bus's stream model."""
    rows: list[object] = []
    for name in sorted(NETWORK_PROFILES):
        prof = NETWORK_PROFILES[name]
        for seed in SEEDS:
            for device, links in RADIO_LINKS.items():
                radio = DeviceRadio(prof, seed, device, links, EPOCH)
                for link in sorted(links):
                    size = 1460 if link == "video" else 60
                    rows.append([name, seed, device, link, [radio.decide(link, size, t) for t in TIMES]])
                radio.close()
            bus = StreamModel(prof.link("bus"), seed, "bus", "a->b", epoch=EPOCH)
            rows.append([name, seed, "bus", [bus.decide(t, 200) for t in TIMES]])
            plain = LinkModel(prof.link("video"), seed, "x", "video")
            rows.append([name, seed, "plain", [plain.decide(t, 1460) for t in TIMES]])
            rows.append(blackout_windows(prof.blackouts, seed, "tello1", horizon_s=200.0))
    return _digest(rows)


def test_the_links_decisions_are_unchanged() -> None:
    assert links_decisions() == "49f08ff6b8ca66ff"


def test_the_network_decisions_are_unchanged() -> None:
    assert network_decisions() == "f883d5072d141cc5"
