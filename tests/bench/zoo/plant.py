"""Random motor-drive plants of order 1 to 4 and their simulation (numpy/scipy only).

A plant is assembled from physical blocks:

* input stage: a voltage across the armature (`La`: inductance, a current state; `La0`:
  the current algebraic), a solenoid-like coil with no mechanics (`coil`), a current
  command to an inner current loop (`lag`: a first-order loop, a state; `ideal`: the
  current follows at once) or a torque command (`torque`);
* mechanics: none, one rigid inertia (`rigid`: speed), or two inertias on a shaft
  (`twomass`: motor speed, load speed, shaft twist);
* optionally the output shaft's angle (`pos`), free (an integrator) or held by a return
  spring (a valve-like actuator), and a first-order sensor filter on the output (`filt`).

What real drives add, each drawn per rig: Coulomb friction (smoothed sign), input
saturation, a dead time of whole output samples, load-torque steps, a disturbance on the
delivered input (process noise). The fault: the actuator delivers (1 - gamma) of its
(saturated) command.

All quantities are SI: V, A, N*m, rad/s, rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import eig, solve
from scipy.signal import cont2discrete, lfilter

Array = NDArray[np.float64]


def step_gamma(steps: list[tuple[float, float]], t: Array) -> Array:
    """gamma at the times `t` of a fault given as steps (t0, gamma from t0 on), 0 before
    the first."""
    g = np.zeros_like(t)
    for t0, v in steps:
        g[t >= t0] = v
    return g

INPUT_KINDS = ("voltage", "current", "torque")
OUTPUT_KINDS = ("current", "speed", "position")
ELEC_FOR_INPUT = {"voltage": ("La", "La0", "coil"), "current": ("lag", "ideal"),
                  "torque": ("torque",)}
MECH_STATES = {"none": 0, "rigid": 1, "twomass": 3}


@dataclass(frozen=True)
class Structure:
    """The blocks of a plant (see the module docstring)."""

    in_kind: str
    out_kind: str
    elec: str
    mech: str
    pos: str  # "", "free" or "spring"
    filt: bool
    load_side_sensor: bool = False  # two-mass speed output: load side (else motor side)

    @property
    def order(self) -> int:
        return (int(self.elec in ("La", "coil", "lag")) + MECH_STATES[self.mech]
                + int(bool(self.pos)) + int(self.filt))

    def describe(self) -> str:
        parts = [self.elec]
        if self.mech != "none":
            parts.append(self.mech + ("(load enc)" if self.load_side_sensor else ""))
        if self.pos:
            parts.append(f"pos-{self.pos}")
        if self.filt:
            parts.append("filt")
        return "+".join(parts)


def valid(s: Structure) -> bool:
    if s.elec == "coil" and (s.mech != "none" or s.out_kind != "current"):
        return False
    if s.mech == "none" and not (s.elec == "coil" or (s.elec == "lag" and s.out_kind == "current")):
        return False
    if s.out_kind == "current" and s.elec not in ("La", "coil", "lag"):
        return False
    if s.out_kind == "position" and not s.pos:
        return False
    if s.pos and s.mech == "none":
        return False
    if s.pos == "free" and s.out_kind != "position":
        return False  # a free angle nobody measures is not part of what the output shows
    if s.elec == "lag" and s.out_kind == "current" and s.mech != "none":
        return False  # a current loop's current does not see the mechanics
    if s.load_side_sensor and not (s.mech == "twomass" and s.out_kind == "speed"):
        return False
    return 1 <= s.order <= 4


def structures(in_kind: str, out_kind: str) -> list[Structure]:
    out = []
    for elec in ELEC_FOR_INPUT[in_kind]:
        for mech in MECH_STATES:
            for pos in ("", "free", "spring"):
                for filt in (False, True):
                    for lss in (False, True):
                        s = Structure(in_kind, out_kind, elec, mech, pos, filt, lss)
                        if valid(s):
                            out.append(s)
    return out


@dataclass
class Plant:
    """A linear plant x' = A x + B u + Bl load + Bf friction, y = C x, plus what drives add."""

    structure: Structure
    A: Array
    B: Array  # (n,) the actuator
    Bl: Array  # (n,) a load torque on the output shaft (zeros without mechanics)
    Bf: Array  # (n,) the friction torque on the motor shaft
    C: Array  # (n,)
    u_range: float  # the command's range is +-u_range
    torque_scale: float  # N*m, rated torque (0 without mechanics)
    speed_index: int  # motor-shaft speed state (-1 without mechanics)
    coulomb: float = 0.0  # N*m
    saturation: float | None = None  # the actuator clips |u| at this
    dead: int = 0  # output samples
    process_sigma: float = 0.0  # disturbance on the delivered input, in the input's unit
    load_step: float = 0.0  # N*m, size of the load steps (0: none)
    params: dict[str, float] = field(default_factory=dict)

    @property
    def order(self) -> int:
        return int(self.A.shape[0])

    @property
    def integrating(self) -> bool:
        return self.structure.pos == "free"

    def poles(self) -> NDArray[np.complex128]:
        return np.asarray(np.linalg.eigvals(self.A), dtype=np.complex128)

    def dominant_tau(self) -> float:
        """The slowest non-integrating time constant, s."""
        re = np.abs(self.poles().real)
        re = re[re > 1e-9]
        return float(1.0 / re.min()) if re.size else 1.0


def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def build(rng: np.random.Generator, s: Structure, rate: float) -> Plant:
    """Random physical parameters for the structure `s` sampled at `rate` Hz."""
    T = 1.0 / rate
    names: list[str] = []

    def add(name: str) -> int:
        names.append(name)
        return len(names) - 1

    i_x = add("i") if s.elec in ("La", "coil", "lag") else -1
    w1 = w2 = tw = -1
    if s.mech == "rigid":
        w1 = w2 = add("w")
    elif s.mech == "twomass":
        w1, w2, tw = add("w1"), add("w2"), add("twist")
    th = add("theta") if s.pos else -1
    yf = add("yf") if s.filt else -1
    n = len(names)
    A = np.zeros((n, n))
    B = np.zeros(n)
    Bl = np.zeros(n)
    Bf = np.zeros(n)
    C = np.zeros(n)
    p: dict[str, float] = {}

    # -- input stage and its scales
    kt = 0.0  # N*m per A (torque per unit of i)
    torque_rated = 0.0
    if s.elec == "coil":
        v_r = float(rng.choice([12.0, 24.0, 48.0]))
        r = _logu(rng, 1.0, 30.0)
        tau = _logu(rng, max(2 * T, 2e-3), 0.2)
        A[i_x, i_x] = -1.0 / tau
        B[i_x] = 1.0 / (tau * r)
        u_range = v_r
        p.update(R=r, L=tau * r)
    elif s.elec in ("La", "La0"):
        v_r = float(rng.choice([12.0, 24.0, 48.0, 96.0, 300.0]))
        i_r = _logu(rng, 0.5, 40.0)
        ra = v_r / (i_r * _logu(rng, 3.0, 15.0))
        ke = v_r / _logu(rng, 100.0, 1000.0)
        kt = ke
        tau_em = _logu(rng, max(3 * T, 5e-3), 1.0)
        J = tau_em * ke * kt / ra
        b = J / _logu(rng, 2.0, 30.0)
        u_range = v_r
        torque_rated = kt * i_r
        p.update(Ra=ra, Ke=ke, J=J, b=b)
        if s.elec == "La":
            la = _logu(rng, 0.2e-3, 20e-3) * ra
            p["La"] = la
    else:  # lag, ideal, torque
        kt = _logu(rng, 0.02, 1.0) if s.elec != "torque" else 1.0
        i_r = _logu(rng, 0.5, 40.0)
        torque_rated = kt * i_r if s.elec != "torque" else _logu(rng, 0.05, 20.0)
        w_ss = _logu(rng, 50.0, 600.0)
        b = torque_rated / w_ss
        tau_mech = _logu(rng, max(3 * T, 0.02), 2.0)
        J = b * tau_mech
        u_range = i_r if s.elec != "torque" else torque_rated
        p.update(Kt=kt, J=J, b=b)
        if s.elec == "lag":
            lo = max(T / 2, 0.3e-3) if s.mech == "none" else 0.3e-3
            p["tau_c"] = _logu(rng, lo, max(lo * 1.5, 20e-3 if s.mech == "none" else 10e-3))

    # -- mechanics
    if s.mech != "none":
        J, b = p["J"], p["b"]
        if s.mech == "rigid":
            J1 = J2 = J
            A[w1, w1] -= b / J
        else:
            a = rng.uniform(0.3, 0.8)
            J1, J2 = a * J, (1 - a) * J
            jeq = J1 * J2 / (J1 + J2)
            f_r = _logu(rng, 3.0, max(4.0, min(50.0, rate / 10)))
            k = jeq * (2 * math.pi * f_r) ** 2
            c = 2 * rng.uniform(0.05, 0.3) * math.sqrt(k * jeq)
            A[w1, w1] -= (b / 2 + c) / J1
            A[w1, w2] += c / J1
            A[w1, tw] -= k / J1
            A[w2, w2] -= (b / 2 + c) / J2
            A[w2, w1] += c / J2
            A[w2, tw] += k / J2
            A[tw, w1] += 1.0
            A[tw, w2] -= 1.0
            p.update(J1=J1, J2=J2, k_shaft=k, c_shaft=c, f_res=f_r)
        Bf[w1] = 1.0 / J1
        Bl[w2] = 1.0 / J2
        # torque from the input stage
        if s.elec == "La":
            la, ra, ke = p["La"], p["Ra"], p["Ke"]
            A[i_x, i_x] = -ra / la
            A[i_x, w1] = -ke / la
            B[i_x] = 1.0 / la
            A[w1, i_x] += kt / J1
        elif s.elec == "La0":
            ra, ke = p["Ra"], p["Ke"]
            A[w1, w1] -= kt * ke / (ra * J1)
            B[w1] += kt / (ra * J1)
        elif s.elec == "lag":
            A[i_x, i_x] = -1.0 / p["tau_c"]
            B[i_x] = 1.0 / p["tau_c"]
            A[w1, i_x] += kt / J1
        elif s.elec == "ideal":
            B[w1] += kt / J1
        else:  # torque
            B[w1] += 1.0 / J1
        if s.pos:
            A[th, w2] = 1.0
            if s.pos == "spring":
                jt = J1 + J2 if s.mech == "twomass" else J
                f_s = _logu(rng, 0.3, max(0.5, min(5.0, rate / 20)))
                ks = jt * (2 * math.pi * f_s) ** 2
                A[w2, th] -= ks / J2
                # a return spring with too little damping rings for ever: damp it to 0.15
                damp = b + (p["Ke"] ** 2 / p["Ra"] if s.elec in ("La", "La0") else 0.0)
                zeta = damp / (2 * math.sqrt(ks * jt))
                if zeta < 0.15:
                    extra = (0.15 - zeta) * 2 * math.sqrt(ks * jt)
                    A[w2, w2] -= extra / J2
                p.update(k_spring=ks, f_spring=f_s)
    elif s.elec == "lag":  # current loop alone: current in, current out
        A[i_x, i_x] = -1.0 / p["tau_c"]
        B[i_x] = 1.0 / p["tau_c"]

    # -- the measured quantity and the sensor filter
    if s.out_kind == "current":
        meas = np.eye(n)[i_x]
    elif s.out_kind == "speed":
        meas = np.eye(n)[w2 if s.load_side_sensor else w1]
    else:
        meas = np.eye(n)[th]
    if s.filt:
        tau_f = _logu(rng, T, 5 * T)
        A[yf] += meas / tau_f
        A[yf, yf] -= 1.0 / tau_f
        C[yf] = 1.0
        p["tau_filter"] = tau_f
    else:
        C[:] = meas
    return Plant(structure=s, A=A, B=B, Bl=Bl, Bf=Bf, C=C, u_range=u_range,
                 torque_scale=torque_rated, speed_index=w1, params=p)


@dataclass(frozen=True)
class Drive:
    """What the plant is fed on the fine grid (step h), all arrays of one length."""

    u_cmd: Array  # the command, as it is on the bus (SI)
    gamma: Array  # the true loss of effectiveness
    load: Array  # load torque, N*m


def simulate(plant: Plant, h: float, sub: int, drive: Drive,
             rng: np.random.Generator) -> Array:
    """The noise-free output at every `sub`-th point of the fine grid (the sample instants).

    The plant starts at the steady state of its first command (at rest for an integrating
    plant). The delivered input is (1 - gamma) * clip(command delayed by the dead time),
    plus the process disturbance.
    """
    nfine = drive.u_cmd.size
    u = drive.u_cmd
    if plant.dead:
        d = plant.dead * sub
        u = np.concatenate([np.full(d, u[0]), u[:-d]])
    if plant.saturation is not None:
        u = np.clip(u, -plant.saturation, plant.saturation)
    u_del = (1.0 - drive.gamma) * u
    if plant.process_sigma > 0:
        u_del = u_del + rng.normal(0.0, plant.process_sigma, nfine)
    n = plant.order
    Bfull = np.column_stack([plant.B, plant.Bl, plant.Bf])
    Ad, Bd, _, _, _ = cont2discrete((plant.A, Bfull, np.eye(n), np.zeros((n, 3))), h,
                                    method="zoh")
    w_eps = 0.0
    if plant.coulomb > 0:
        # smoothed sign, wide enough that the explicit friction step (held over an output
        # period) cannot chatter
        jf = 1.0 / plant.Bf[plant.speed_index]
        w_eps = max(4.0 * plant.coulomb * h * sub / jf, 1e-3)

    # steady state of the first input
    x0 = np.zeros(n)
    if not plant.integrating:
        fric = 0.0
        for _ in range(8):
            rhs = plant.B * u_del[0] + plant.Bl * drive.load[0] + plant.Bf * fric
            x0 = solve(plant.A, -rhs)
            if plant.coulomb <= 0:
                break
            fric = -plant.coulomb * math.tanh(x0[plant.speed_index] / w_eps)

    if plant.coulomb <= 0:
        X = _modal(Ad, Bd, x0, np.column_stack([u_del, drive.load, np.zeros(nfine)]))
        if X is not None:
            return np.asarray(X[::sub] @ plant.C, dtype=np.float64)
    # the loop, one output period a step (the friction held over it): Coulomb friction
    # (or a defective Ad); the inputs' part of each period is summed beforehand
    n_out = nfine // sub
    W = np.column_stack([u_del, drive.load])[: n_out * sub].reshape(n_out, sub, 2)
    powers = [np.linalg.matrix_power(Ad, sub - 1 - j) for j in range(sub)]
    G = sum(W[:, j, :] @ (powers[j] @ Bd[:, :2]).T for j in range(sub))
    AT = np.linalg.matrix_power(Ad, sub)
    bfT = sum(powers[j] @ Bd[:, 2] for j in range(sub))
    ys = np.empty(n_out)
    x = x0.copy()
    c = plant.C
    si, tc = plant.speed_index, plant.coulomb
    for k in range(n_out):
        ys[k] = c @ x
        f = -tc * math.tanh(x[si] / w_eps) if tc > 0 else 0.0
        x = AT @ x + G[k] + bfT * f
    return ys


def _modal(Ad: Array, Bd: Array, x0: Array, W: Array) -> Array | None:
    """x(k+1) = Ad x(k) + Bd w(k) mode by mode with lfilter; None if Ad is defective."""
    lam, V = eig(Ad)
    if np.linalg.cond(V) > 1e7:
        return None
    Vi = np.linalg.inv(V)
    G = W @ (Vi @ Bd).T  # (N, n) complex
    z0 = Vi @ x0
    G = G.astype(np.complex128)
    Z = np.empty_like(G)
    for j in range(lam.size):
        s = lfilter([1.0], [1.0, -lam[j]], G[:, j], zi=np.array([lam[j] * z0[j]]))[0]
        Z[0, j] = z0[j]
        Z[1:, j] = s[:-1]
    return np.asarray((Z @ V.T).real, dtype=np.float64)
