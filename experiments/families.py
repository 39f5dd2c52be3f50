"""The accuracy suite's scene families and its ``--seeds`` syntax: plain data, shared by the suite and
its command-line parser (which imports nothing heavy)."""
from __future__ import annotations

#: family name: what its scenes are (experiments.suite.family_config builds them)
FAMILIES = {
    "panels": "frontal panels, a window of the real FLIVVER run",
    "rotation": "frontal panels with 3-axis rotation (yaw, pitch, roll up to ±5°, 0.3-1.5 Hz)",
    "corridor": "corridor (floor, ceiling, walls, end wall ~12 m beyond), to 1 m/s",
    "fast": "corridor, to 2 m/s, starting in motion",
    "offaxis": "frontal panels, heading 5-9° sideways and up to 4° vertically off the optical axis",
    "dim": "frontal panels, 35% brightness, half contrast, pixel noise 6 grey levels",
    "ground": "outdoor ground plane to the horizon, objects, backdrop 50-200 m, sky; to 1.5 m/s",
    "rest": "frontal panels, random smooth run to 0.6 m/s starting at rest",
    "moving": "frontal panels, random smooth run to 0.6 m/s starting in motion",
    "mixed": ("held out: a world drawn among panels (side walls or not), corridor and ground, turning "
              "(3-axis, 2-5°), heading up to 9° × 4° off the axis, to 0.6-2.5 m/s, from rest or in "
              "motion, pixel noise 1-6 grey levels; every seed another combination"),
}


#: families run only when named (``--families saccadic``), not in "all": fly flight, where the camera's
#: pipeline is still being built for it, and the real-world platforms (stimuli.platforms), where the
#: estimator's indoor priors are being adapted to them
EXTRA_FAMILIES = {
    "saccadic": ("fly flight (lobula scene --flight saccadic): straight segments of 0.2-2 s, body saccades of "
                 "20-90° in 50-100 ms, 0.1-1 m/s; the panels, corridor and meadow worlds in turn (seed mod 3)"),
    "drone": ("drone flight, named only (the estimator is being adapted to it): from near rest to 5-15 m/s in "
              "2-6 s, then cruise; 3-30 m above ground with objects, backdrop 100-2,000 m, sky; gimbal camera "
              "tilted 0-20° down, residual rotation 0.1-0.4°; propeller vibration 0.3-1 m/s² rms at 50-200 Hz, "
              "aliased by the IMU's 250 Hz sampling"),
    "road": ("road vehicle, named only (the estimator is being adapted to it): 5-25 m/s with stop-and-go "
             "(braking at 2.5-8 m/s² to 0-0.3 m/s, 0.5-2 s stopped, off again at 1.5-3.5 m/s²), pitch with the "
             "acceleration, bounce and lane wander; ground world with roadside objects, camera 1-2 m up"),
    "walking": ("hand-held walking, named only (the estimator is being adapted to it): 1-2 m/s from rest or in "
                "stride, gait surge 5-15% at 1.7-2.2 Hz, bounce 1.5-4 cm, sway 1-4 cm, hand rotation 1-4° per "
                "axis at 0.2-2.5 Hz (tens of °/s); the ground world on even seeds, the corridor on odd ones"),
}
#: every family a suite can run
ALL_FAMILIES = {**FAMILIES, **EXTRA_FAMILIES}


def parse_seeds(text: str) -> int | list[int]:
    """``--seeds``: "3" means seeds 0, 1, 2; "100,101" means exactly those seeds; "7," seed 7 alone."""
    try:
        if "," not in text:
            n = int(text)
            if n < 1:
                raise ValueError
            return n
        # one trailing comma makes a list of one seed ("7," is seed 7, "7" is seeds 0..6)
        return [int(t) for t in (text[:-1] if text.endswith(",") else text).split(",")]
    except ValueError:
        raise ValueError(f"--seeds must be a positive count or a comma-separated list of seeds, got {text!r}") from None
