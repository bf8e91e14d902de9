"""The job manager's parameters (design §6; seed 004 Table 3.1 symbols in brackets)."""
from __future__ import annotations

import msgspec

from services.lib.lidar.sanity import SETTLE_TIME


class JobManagerParams(msgspec.Struct, forbid_unknown_fields=True):
    """Defaults from design §6 / seed 004 Table 3.1 (symbol in brackets)."""

    search_height: float = 5.0  # [H] m, world z of the sweep
    scan_spacing: float = 20.0  # m between lawnmower lines (the LiDAR sees well beyond ±10 m)
    landing_margin: float = 15.0  # s before the mission's end at which to land
    status_rate_hz: float = 5.0
    sensor_timeout: float = 1.0  # s of silent LiDAR or odometry before an emergency landing
    height_tolerance: float = 0.3  # m below search_height that counts as "at height"
    airborne_height: float = 0.3  # m above the ground that counts as airborne
    command_repeat: float = 2.0  # s between re-sends of the current command (0: only on change)
    detection_gate: float = 3.0  # [d_e] m: a detection this close to the locked target is the target
    filter_switch_distance: float = 5.5  # [D_k] m: GOING_TO_TARGET hands over to DESTROYING inside it
    target_time: float = 3.0  # [t_m] s: unseen this long = lost; seen this long = confirmed for attack
    # frames (and scans) of the last t_m that must agree on a camera blob before it is locked (a
    # confirmed track there counts as agreed): a single camera blob starts no engagement
    lock_sightings: int = 3
    checking_timeout: float = 30.0  # [T_c] s
    going_timeout: float = 30.0  # [T_g] s
    destroying_timeout: float = 20.0  # [T_d] s (for a mover: since its latest close pass)
    close_pass_distance: float = 2.0  # m: a just-seen mover this close restarts T_d (it is being got at)
    forbidden_radius: float = 4.5  # [r_f] m
    forbidden_lifetime: float = 15.0  # [t_f] s
    forbidden_tries: int = 2  # [n_f] attacks at one place before it is forbidden
    blocked_time: float = 2.0  # s the planner finds every approach to a static target blocked before it is forbidden
    partner_timeout: float = 15.0  # [t_s] s without a partner's status: it has fallen (revenge mode)
    rejoin_time: float = 3.0  # s a fallen partner must fly normally again before it gets an area back
    lost_link_time: float = 1.5  # s without a partner's status (or its token gone): it is stale (lost-link rule)
    no_fly_margin: float = 5.0  # m beyond safety_distance around an unaccounted partner's last position
    stop_speed: float = 0.5  # m/s: the stop manoeuvre is over
    detection_max_age: float = 0.35  # s: older detections are not "in view"
    min_target_height: float = 1.0  # m above the ground: lower detections are no targets
    replan_distance: float = 0.3  # m the locked target must move before a new approach/attack goes out
    attack_pass_margin: float = 0.5  # m past the target (along the attack) that counts as through it
    attack_done_speed: float = 1.0  # m/s: the overshoot is flown out
    attack_level_speed: float = 0.3  # m/s: an attack starts once the vehicle climbs or sinks slower than this
    moving_speed: float = 1.0  # m/s: a target whose track is faster is intercepted
    motion_sigmas: float = 3.0  # ... and whose fitted speed is this many standard errors above 0 (not noise)
    track_gate: float = 2.0  # m between a detection and a track for them to be the same object
    intercept_replan_distance: float = 0.3  # m a new prediction must part from the sent one (over 1 s ahead) before a new intercept goes out
    intercept_refresh: float = 1.0  # s: an intercept's prediction is sent again at least this often (below the planner's pursuit_trust)
    # s: an interception is taken up (after a yield or give-way, or on a lock) only on a sighting at most this
    # old; an older one has the UAV hold and look until the target is seen again (or lost after t_m)
    intercept_sighting_age: float = 1.0
    velocity_window: float = 1.0  # s of detections the target filter fits a target's velocity to
    filter_sigma: float = 0.15  # m, target filter measurement noise
    filter_process_sigma: float = 0.05  # m/√s, target filter process noise (a balloon sways)
    streak_gap: float = 1.0  # s without a detection that breaks "seen continuously"
    reliable_range: float = 20.0  # m: a target farther than this shows in some scans only; unseen time counts inside
    claim_radius: float = 4.5  # m around a partner's target that is left to it
    area_overlap: float = 2.0  # m beyond its working area a UAV still takes a target (one on the line: both may)
    safety_distance: float = 5.0  # m: closer than this to a partner, the lower-priority UAV yields
    # m above the highest point of the partner's plan near it a yielding UAV climbs to (when holding
    # where it is would not keep it clear): more than safety_distance, so a partner passing below is no breach
    vertical_separation: float = 6.0
    separation_hysteresis: float = 2.0  # m beyond safety_distance before a yield ends
    # s: a partner predicted (both at their current velocities) to come within safety_distance this
    # soon is treated as one already there. Two UAVs closing at 10 m/s (two sweeps head-on) brake from
    # 5 m/s in 1.7 s (attack profile) and a yielding one climbs clear in about 1.5 s more
    separation_lookahead: float = 3.0
    # Separation planned ahead (team.py, plans.py): the statuses carry the next plan_horizon s of each
    # UAV's reference every plan_step s; a partner's plan must keep plan_widen_rate m more per second
    # of its age. 6 s: braking from 8.3 m/s (2.8 s at the attack profile) and climbing clear after
    plan_horizon: float = 6.0
    plan_step: float = 0.25
    plan_widen_rate: float = 2.0
    sweeping_speed: float = 5.0  # m/s, constraint profile "sweeping" (scan, approach, climbs)
    sweeping_acceleration: float = 1.5  # m/s²
    attack_speed: float = 8.3  # m/s, constraint profile "attack" (attack, intercept)
    attack_acceleration: float = 3.0  # m/s²
    # Flying without GNSS (the localizer's health in the odometry): "degraded" flies every command
    # with the profile "degraded" at this speed at most; "lost" holds position, and lost for
    # sensor_timeout lands as a silent LiDAR does (an emergency landing)
    degraded_speed: float = 2.0  # m/s
    # s after a LiDAR scan or camera frame that failed its sanity check (PointCloud.sanity) during
    # which that sensor's detections are not acted on (services/lib/lidar/sanity.py)
    sensor_settle_time: float = SETTLE_TIME
