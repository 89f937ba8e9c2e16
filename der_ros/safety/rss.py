"""The RSS longitudinal safe distance between two cars driving in the same direction.

Responsibility-Sensitive Safety (Shalev-Shwartz, Shammah and Shashua 2017, definition 1): the
rear car, during its response time ``rho``, may still accelerate at up to ``accel_max``; then it
brakes at no less than ``brake_min``; the front car may brake at up to ``brake_max`` all along.
The gap is safe when it is larger than what the rear car needs to stop behind the front car::

    d_min = [ v_r rho + 1/2 a_acc rho^2 + (v_r + rho a_acc)^2 / (2 b_min) - v_f^2 / (2 b_max) ]_+

Written here in plain Python (no dependency: Intel's ``ad-rss`` has wheels for Linux x86_64 only);
``test/test_safety_rss.py`` checks it against ``ad-rss``'s
``calculateSafeLongitudinalDistanceSameDirection`` on a grid of situations where that library is
installed (requirements-dev.txt).
"""

from __future__ import annotations

__all__ = ["safe_longitudinal_distance"]


def safe_longitudinal_distance(
    v_rear: float, v_front: float, response_time: float, accel_max: float, brake_min: float, brake_max: float
) -> float:
    """RSS ``d_min`` in metres (bumper to bumper) for a rear car at ``v_rear`` behind one at ``v_front``.

    Speeds in m/s (negative speeds count as 0: cars do not reverse here); accelerations are
    magnitudes in m/s^2 (``brake_min`` and ``brake_max`` > 0). A gap is safe when it is *strictly*
    larger than the result (as ``ad-rss`` decides).
    """
    v_r = v_rear if v_rear > 0.0 else 0.0
    v_f = v_front if v_front > 0.0 else 0.0
    v_after = v_r + response_time * accel_max
    d = (
        v_r * response_time
        + 0.5 * accel_max * response_time * response_time
        + v_after * v_after / (2.0 * brake_min)
        - v_f * v_f / (2.0 * brake_max)
    )
    return d if d > 0.0 else 0.0
