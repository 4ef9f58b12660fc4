"""The Rerun 3-D viewer of a flight: replayed from a run directory (`flightstack view RUN_DIR`) or live
while it flies (`--viewer` on run/sim/fly/agent, a `flightstack.runtime.taps.TickTap`).

Rerun (rerun-sdk, the optional extra `viewer`, pinned to `rerun_import.PINNED_VERSION` because its logging
and read-back APIs change between releases) is imported lazily: nothing here imports it at module level,
and without it `rerun_import.load_rerun` raises `ViewerUnavailable` naming
`pip install 'flightstack[viewer]'`.

One Rerun recording per run, one timeline `mission_time` (seconds of the mission clock, a duration), every
mode under its own entity path `/<mode>/...` so that modes flown one after the other (none, local, dgp)
share the timeline and can be compared side by side (`layout` lists every path and the rates):

    /<mode>/world/target              Transform3D: true target pose g_w0 (Σw, m; yaw about z)
    /<mode>/world/drone<i>            Transform3D: drone i's true pose g_wi
    /<mode>/world/drone<i>/camera     its camera's fixed extrinsic (mount, offset), static
    /<mode>/world/drone<i>/camera/image   Pinhole (frustum), live camera images (JPEG)
    /<mode>/world/estimate<i>         Transform3D: drone i's estimate ḡ_w,i of the target pose
    /<mode>/world/trails/<body>       LineStrips3D: the body's path over the last `layout.TRAIL_S` s
    /<mode>/<signal>/drone<i>         Scalars: e_c, e_e (and their norms), mu_fused, mu_own, var_own, ...
    /<mode>/events                    TextLog: every event of the mode (safety events as WARN)
    /mission/regions/drone<i>         Boxes3D: drone i's GP expert region (static)
    /mission/training/drone<i>        Points3D: its expert's training inputs (static)

Modules: `rerun_import` (the lazy import), `layout` (paths, rates), `scene` (static entities),
`mode_logger` (rows of one mode → columns), `blueprint` (the default view layout), `sinks` (spawn,
connect, save), `replay` (a run directory → a recording), `live` (the tap).
"""
