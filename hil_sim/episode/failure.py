"""Why an episode failed, in words: the verdict of a lockstep episode (hil_sim.episode.lockstep)
and of a real-time one (hil_sim.episode.realtime), from its metrics and the controller's report."""
from __future__ import annotations

from hil_sim.episode.patrol import patrol_failure_reason


def failure_reason(metrics: dict, controller: dict) -> str | None:
    """Why the episode failed, in words (None on success), and after a calibration mismatch (the
    partition fell back to all-fixed) that mismatch, the likely cause, said with it."""
    reason = _first_failure(metrics, controller)
    mismatch = controller.get("calibration", {}).get("mismatch")
    if reason is not None and mismatch is not None:
        reason += f" (after a calibration mismatch: {mismatch})"
    return reason


def _first_failure(metrics: dict, controller: dict) -> str | None:
    """The first that applies: fixed contact; a latched safety stop; an input fault the robot was
    holding for at the end; never became active; a patrol's missed goals or its early end
    (hil_sim.episode.patrol); time limit while blocked (no path); stalled without progress with a
    valid reference path; the controller's goal not the world's (odometry drift); time limit.
    """
    if metrics["success"]:
        return None
    if metrics["fixed_contacts"]:
        hit = [o["name"] for o in metrics["obstacles"] if o["class"] != "movable" and o["contact_count"]]
        return f"fixed contact: {', '.join(hit)} ({metrics['fixed_contacts']} contact events)"
    state = controller["state"]
    if state == "STOPPED":
        return f"safety stop: {controller['stop_reason']}"
    base_faults = [f["reason"] for f in controller["input_faults"] if f["stream"] == "0x211"]
    if state == "HOLDING":
        if controller["hold_reason"] in base_faults:
            return f"base not ready: {controller['hold_reason']} (held still at the time limit)"
        return f"sensor stale: {controller['hold_reason']} (held still at the time limit)"
    if state == "INITIALIZING":
        faults = "; ".join(f["reason"] for f in controller["input_faults"]) or "base not ready"
        if controller["restarts"]:
            return f"start-up sequence not complete after {controller['restarts']} restarts: {faults}"
        return f"never became active: {faults}"
    if "patrol" in metrics:
        reason = patrol_failure_reason(metrics)
        if reason is not None:
            return reason
    if state == "GOAL_REACHED":
        return (
            f"odometry drift: the controller reached the goal in its odom frame, the robot is "
            f"{metrics['final_distance_to_goal_m']:.2f} m from it"
        )
    if controller.get("blocked_now"):
        return (
            f"time limit while blocked: no path to the goal in the local map for the last "
            f"{controller['blocked_for_s']:.1f} s ({controller['blocked_ticks']} blocked ticks)"
        )
    if controller.get("stalled_now") or controller.get("stalls"):
        return (
            f"stalled without progress with a valid reference path: {controller['stalls']} stalls, "
            f"{controller['backoffs']} backoffs and {controller.get('correcting_events', 0)} corrections did not "
            f"free it, "
            f"{metrics['final_distance_to_goal_m']:.2f} m from the goal"
        )
    return f"time limit: {metrics['final_distance_to_goal_m']:.2f} m from the goal"
