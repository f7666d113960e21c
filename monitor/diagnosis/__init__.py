"""Fault diagnosis by fuzzy c-means clustering of the estimated loss of effectiveness.

The paper (Liu et al., Int. J. Fuzzy Syst. 22(1), 2020, section 4) collects the fault
information in a set S (55), clusters it with fuzzy c-means (56)-(62) into three groups
(fault-free, fault, outage) and reads two thresholds F1 < F2 off the clusters, which split
the fault quantity into the regions of (76):

    F < F1          fault-free
    F1 <= F <= F2   fault
    F > F2          outage

Which quantity is clustered
---------------------------
The paper clusters its fault function f^ = -B gamma^ u, which is in state units: it scales
with the input voltage u and with the input matrix B, so thresholds found on one motor (or
at one supply voltage) do not carry over to another. This module clusters the *scale-free*
estimate gamma^ of the actuator loss of effectiveness (3)-(5) instead: gamma = 0 is
fault-free and gamma = 1 is a complete outage, for every motor and voltage. The paper's
reported F1 = 0.3, F2 = 1 are in its own units and are deliberately not hard-coded; see
`DEFAULT_THRESHOLDS` for the gamma defaults and `calibrate` for thresholds from a run.

Fuzzy c-means, as implemented
-----------------------------
For points x_k (k = 1..N) and centres c_i (i = 1..c), with distances d_ik = |x_k - c_i|
and fuzzifier m > 1, the objective (56)/(61) is J_m = sum_i sum_k u_ik^m d_ik^2 subject to
sum_i u_ik = 1 for every k (59)/(62). Its stationary conditions are

    u_ik = 1 / sum_j (d_ik / d_jk)^(2/(m-1))          (58)
    c_i  = sum_k u_ik^m x_k / sum_k u_ik^m             (57)

and alternating them decreases J_m monotonically (Bezdek 1981). The paper prints (58) with
the squared-distance ratio and no exponent, which is m = 2; its (57) weights the points by
u rather than u^m, which is not the minimiser paired with (58), and its (56) divides by
sum u. We use the consistent Bezdek pair above, with m = 2 by default and any m > 1
accepted. A point that coincides with a centre (d_ik = 0) belongs wholly to that cluster
(the limit of (58)); memberships are evaluated in log space, so no NaN or overflow arises
even for m close to 1.

Thresholds
----------
Because u_ik is proportional to d_ik^(-2/(m-1)), two clusters i and j have equal
membership at x iff d_i(x) = d_j(x), i.e. |x - c_i| = |x - c_j|: for 1-D data that is the
midpoint (c_i + c_j) / 2, whatever the fuzzifier m and whatever the other centres (they
only change the common normaliser). So F1 and F2 are the midpoints of adjacent sorted
centres, exactly.

Online use
----------
`classify` is (76) applied to one value. `OnlineClassifier` adds a hysteresis band around
each threshold and a dwell time measured in sample timestamps, so noise near a threshold
does not make the reported state flicker. `HealthState` values are the numbers sent on the
CAN bus. `MismatchDetector` raises a model-mismatch flag beside the state (the innovations
say the model does not explain the plant); `reported_state` is the state reported with it.
These rules exist once, compiled, as steps over a node's state vector (`rules`): the
monitor's engines call them per sample and tick, and the two classes are views of them.
"""

from monitor.diagnosis.classifier import (
    HealthState,
    MismatchDetector,
    OnlineClassifier,
    classify,
    reported_state,
    transitions,
)
from monitor.diagnosis.fcm import (
    FCMResult,
    calibrate,
    fcm_memberships,
    fuzzy_c_means,
    thresholds_from_clusters,
)
from monitor.diagnosis.thresholds import (
    DEFAULT_THRESHOLDS,
    DiagnosisError,
    DiagnosisSpec,
    Thresholds,
    load_thresholds,
    save_thresholds,
)

__all__ = [
    "DEFAULT_THRESHOLDS",
    "DiagnosisError",
    "DiagnosisSpec",
    "FCMResult",
    "HealthState",
    "MismatchDetector",
    "OnlineClassifier",
    "Thresholds",
    "calibrate",
    "classify",
    "fcm_memberships",
    "fuzzy_c_means",
    "load_thresholds",
    "reported_state",
    "save_thresholds",
    "thresholds_from_clusters",
    "transitions",
]
