"""`replay_file`: one bus log through decode, estimation and diagnosis a chunk at a time.

The columnar counterpart of ``feed_log(MonitorPipeline(db, cfg, sink=sink), read_log(path))``
with the same diagnosis events, the same counters and the same samples (see the package
docstring for what differs: only when counter snapshots reach the sink).
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
from collections.abc import Callable, Iterable
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from monitor.bus.cia402 import (
    IGNORED_NOT_OPERATIONAL,
    IGNORED_PROTOCOL,
    drive_watch,
    report_counter,
)
from monitor.columnar import kernels as K
from monitor.columnar.decode import REASONS, DecodedChunk, NotColumnar, RouteTable
from monitor.columnar.reader import DEFAULT_CHUNK_FRAMES, FrameChunk, read_chunks
from monitor.columnar.sinks import SinkRouter
from monitor.diagnosis import HealthState
from monitor.diagnosis.rules import FLAG_CAUSES, FLAGGED, HEALTH_CAUSES, REPORTED, new_state
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.estimation.model import DiscreteModel
from monitor.pipeline import MonitorConfig, admission
from monitor.pipeline import counters as C
from monitor.pipeline.admission import DROP, NO_COUNTER
from monitor.pipeline.counters import Counters
from monitor.pipeline.events import (
    HEALTH,
    MODEL_MISMATCH,
    Diagnosis,
    DiagnosisEvent,
    SampleColumns,
    drive_event,
    error_frame_event,
)
from monitor.pipeline.feed import replay_frames
from monitor.pipeline.samples import delayed, held_column, no_past
from monitor.sinks.base import Sink

__all__ = ["ReplayResult", "columnar_obstacle", "replay_chunks", "replay_file"]

log = logging.getLogger("motor_monitor")

_STATES = tuple(HealthState)
_UNKNOWN_ID = REASONS.index("unknown_id")


@dataclass
class ReplayResult:
    """What a replay of one log did.

    frames: frames read; counters: the pipeline's counters at the end; events: every
    `DiagnosisEvent` (health transitions and model-mismatch flag changes), in order; nodes:
    per node its final state, model-mismatch flag, gamma^, rules and samples (as
    `MonitorPipeline.summary` gives them); columnar: False when the file went
    through the per-frame path, `fallback` says why.
    """

    path: Path | None
    frames: int
    counters: dict[str, int]
    events: list[DiagnosisEvent]
    nodes: dict[int, dict[str, Any]] = field(default_factory=dict)
    columnar: bool = True
    fallback: str | None = None


class _Node:
    """One node's estimator, held inputs and diagnosis state between chunks."""

    def __init__(self, node: int, model: DiscreteModel, cfg: MonitorConfig,
                 cls_prm: NDArray[np.float64]) -> None:
        self.node = node
        self.model = model
        self.cfg = cfg
        self.T = 1.0 / cfg.rate
        self.est = FuzzyUKF(model, cfg.estimator)
        self.u = np.zeros(model.m)  # the held inputs (`monitor.pipeline.samples`)
        self.u_seen = np.zeros(model.m, np.bool_)
        self.u_past = no_past(model.m)  # held inputs of the last input_delay samples
        self.truth = math.nan
        self.has_truth = False
        self.admission = admission.new_state()  # last admitted sample, resumption pending
        self.diag = new_state(cls_prm)  # the diagnosis rules' state (`monitor.diagnosis.rules`)
        self.gamma = np.zeros(model.m)  # the estimator's latest gamma^ (fresh: zeros)
        self.rules = self.est.out.rules
        self.samples = 0

    def restart(self) -> None:
        self.est = FuzzyUKF(self.model, self.cfg.estimator)
        self.gamma = np.zeros(self.model.m)
        self.rules = self.est.out.rules


class _Replay:
    def __init__(self, db: Any, cfg: MonitorConfig, sink: Sink) -> None:
        self.cfg = cfg
        self.sink = sink
        self.model = cfg.plant().discretize(1.0 / cfg.rate)
        self.table = RouteTable.of(db, self.model.m, self.model.p)
        self.secoc = bool(getattr(db, "secoc_enabled", False))
        self.router = SinkRouter(sink)
        self.counters = Counters()
        self.nodes: dict[int, _Node] = {}
        self.cls_prm = cfg.diagnosis_params(self.model.p)
        routes = self.table.routes
        self.stream_of = np.array([r.stream for r in routes] or [0], np.int64)
        self.output_only = np.array([bool(r.outputs) and not r.inputs and r.truth is None
                                     for r in routes] or [False])
        self.alive_last = np.full(max(1, len(self.table.streams)), -1, np.int64)
        self.route_node = np.array([r.node for r in routes] or [0], np.int64)
        not_read = [admission.not_read(r.kind, r.node, cfg.nodes, self.secoc) for r in routes]
        self.skip_names = sorted({x for x in not_read if x is not None})
        self.route_skip = np.array([0 if x is None else 1 + self.skip_names.index(x)
                                    for x in not_read] or [0], np.int64)
        self.drives = drive_watch(db)  # a CANopen rig's drives, as the per-frame engine
        self.held: set[int] = set()  # nodes whose drive said it was not operational
        self.resume_rows: dict[int, NDArray[np.int64]] = {}  # this chunk's resumptions
        self.last_tick = np.array([-math.inf])
        self.offset = 0
        self.events: list[DiagnosisEvent] = []
        self.warned: set[str] = set()
        FuzzyUKF(self.model, cfg.estimator)  # compiled kernels loaded before the first chunk
        for n in cfg.nodes or ():
            self._node(n)

    def _node(self, n: int) -> _Node:
        nm = self.nodes.get(n)
        if nm is None:
            nm = _Node(n, self.model, self.cfg, self.cls_prm)
            self.nodes[n] = nm
        return nm

    def _warn(self, key: str, text: str) -> None:
        if key not in self.warned:  # the first of each kind per file (per-frame: rate-limited)
            self.warned.add(key)
            log.warning("%s", text)

    # ------------------------------------------------------------------------------ chunk

    def chunk(self, c: FrameChunk) -> None:
        n = len(c)
        if n == 0:
            return
        cnt = self.counters
        cnt.received(n, int(c.is_fd.sum()), int((c.is_fd & c.is_esi).sum()))
        events: list[tuple[int, int, int, Any]] = []  # (key, node order, seq, event)
        for i in np.flatnonzero(c.error).tolist():
            self._error_frame(c, i, events)
        dec = self.table.decode(c)
        tick_idx = np.zeros(n, np.int64)  # the frames after which `feed_log` ticks
        nt = K.ticks(c.t, self.last_tick, tick_idx, K.TICK_S)
        tick_idx = tick_idx[:nt]
        rejected = (dec.code > 0) & ~c.error
        # a CANopen rig's drives: their frames are no rig message (unknown_id), read in
        # order (`DriveWatch.unread`: the protocol's own are IGNORED_PROTOCOL), and a lost
        # heartbeat is also found at a tick (a bus gone silent); `gate` holds, per node, the
        # rows after which the drive's operational state changed, from `gate_start` at the
        # chunk's start (the per-frame engine's rule)
        gate: dict[int, list[tuple[int, bool]]] = {}
        gate_start: dict[int, bool] = {}
        if self.drives is not None:
            watch = self.drives
            now = {nd: watch.operational(nd) for nd in watch.nodes}
            gate_start = dict(now)
            protocol = np.zeros(n, np.bool_)
            frames = np.flatnonzero((dec.code == _UNKNOWN_ID) & ~c.error)
            keys = np.sort(np.concatenate([2 * frames, 2 * tick_idx + 1]))  # tick after feed
            for key in keys.tolist():
                i = key // 2
                if key % 2:
                    reports = watch.tick(float(c.t[i]))
                else:
                    m = c.message(i)
                    protocol[i], reports = watch.unread(m.arbitration_id, m.is_extended_id,
                                                        bytes(m.data), float(c.t[i]))
                for r in reports:
                    cnt.inc(report_counter(r))
                    events.append((key, -1, len(events), drive_event(r)))
                    state = watch.operational(r.node)
                    if state != now[r.node]:
                        now[r.node] = state
                        gate.setdefault(r.node, []).append((i, state))
            if protocol.any():
                cnt.inc(IGNORED_PROTOCOL, int(protocol.sum()))
                rejected &= ~protocol
        rej = dec.code[rejected]
        if len(rej):
            for code, k in enumerate(np.bincount(rej).tolist()):
                if k:
                    reason = REASONS[code]
                    cnt.inc(C.rejected(reason), k)
                    self._warn(reason, f"frame rejected ({reason}): {k} in a chunk")
        acc = np.flatnonzero(dec.code == 0)
        ra = dec.route[acc]
        skip = self.route_skip[ra]  # `admission.not_read`, per route
        for j, name in enumerate(self.skip_names):
            k_skip = int((skip == j + 1).sum())
            if k_skip:
                cnt.inc(name, k_skip)
        keep = skip == 0
        acc, ra = acc[keep], ra[keep]
        node = self.route_node[ra]
        self.resume_rows = {}
        if self.drives is not None and len(acc):
            ok = np.ones(len(acc), dtype=bool)
            for nd in np.unique(node).tolist():
                if nd not in gate_start:
                    continue
                sel = node == nd
                changes = gate.get(nd, [])
                rows = np.array([i for i, _ in changes], np.int64)
                after = np.array([gate_start[nd], *(v for _, v in changes)], dtype=bool)
                # a change at row i (a drive frame, or a tick after frame i) holds from i + 1
                mine = after[np.searchsorted(rows, acc[sel], side="left")]
                ok[sel] = mine
                blocked_before = np.concatenate([[nd in self.held], ~mine[:-1]])
                self.resume_rows[nd] = acc[sel][mine & blocked_before]
                if mine[-1]:
                    self.held.discard(nd)
                else:
                    self.held.add(nd)
            if (~ok).any():
                cnt.inc(IGNORED_NOT_OPERATIONAL, int((~ok).sum()))
                acc, ra, node = acc[ok], ra[ok], node[ok]
        first_pos: dict[int, int] = {}
        if len(node):
            uniq, first = np.unique(node, return_index=True)
            for nd, f in sorted(zip(uniq.tolist(), first.tolist(), strict=True),
                                key=lambda x: x[1]):
                if nd not in self.nodes:
                    first_pos[nd] = int(acc[f])
                self._node(nd)
        # alive counters, per (kind, node) stream, in frame order (`admission.alive_verdict`)
        lost = np.full(n, NO_COUNTER, np.int64)
        wrap = np.zeros(n, np.bool_)  # repeated counters `admit` judges by time
        has_c = dec.counter[acc] >= 0
        if has_c.any():
            ci = acc[has_c]
            rc = ra[has_c]
            lz = np.zeros(len(ci), np.int64)
            wz = np.zeros(len(ci), np.bool_)
            K.alive(self.stream_of[rc], dec.counter[ci], self.output_only[rc], self.alive_last,
                    lz, wz)
            lost[ci] = lz
            wrap[ci] = wz
            rep = lz == DROP
            n_rep = int(rep.sum())
            if n_rep:
                cnt.inc(C.E2E_REPEATED, n_rep)
                self._warn("repeat", f"repeated alive counters: {n_rep} frames")
            jump = (lz > 0) & ~wz
            if jump.any():
                cnt.inc(C.E2E_COUNTER_JUMPS, int(jump.sum()))
                cnt.inc(C.E2E_LOST_FRAMES, int(lz[jump].sum()))
            drop = np.zeros(len(acc), np.bool_)
            drop[np.flatnonzero(has_c)[rep]] = True
            acc, ra, node = acc[~drop], ra[~drop], node[~drop]
        order_of = {nd: k for k, nd in enumerate(self.nodes)}
        for nd, nm in self.nodes.items():
            sel = node == nd
            self._node_chunk(nm, c, dec, acc[sel], ra[sel], lost, wrap, tick_idx,
                             first_pos.get(nd, -1), order_of[nd], events)
        self.offset += n
        events.sort(key=lambda e: (e[0], e[1], e[2]))
        for _, _, _, ev in events:
            if isinstance(ev, DiagnosisEvent):
                if ev.kind == HEALTH:
                    cnt.inc(C.transition(ev.state))
                self.events.append(ev)
                self.sink.on_transition(ev)
            elif isinstance(ev, Diagnosis):
                self.sink.on_diagnosis(ev)
            else:
                self.sink.on_bus_event(ev)
        self.sink.on_counters(float(c.t[-1]), cnt)

    def _error_frame(self, c: FrameChunk, i: int, events: list[tuple[int, int, int, Any]]
                     ) -> None:
        self.counters.inc(C.BUS_ERROR_FRAMES)
        names, event = error_frame_event(c.message(i))
        for name in names:
            self.counters.inc(C.bus_error(name))
        self._warn("errframe-" + ",".join(names), event.text)
        events.append((2 * i, -1, len(events), event))  # keys: rows of this chunk

    def _node_chunk(self, nm: _Node, c: FrameChunk, dec: DecodedChunk, fr: NDArray[np.int64],
                    ra: NDArray[np.int64], lost_all: NDArray[np.int64],
                    wrap_all: NDArray[np.bool_], tick_idx: NDArray[np.int64], created: int,
                    order: int,
                    events: list[tuple[int, int, int, Any]]) -> None:
        cnt = self.counters
        cfg = self.cfg
        m = self.model.m
        t_fr = c.t[fr]
        u_fr = dec.u[fr]
        has_u = ~np.isnan(u_fr)
        any_u = has_u.any(axis=1)
        if any_u.any():
            cnt.inc(C.SAMPLES_INPUT, int(any_u.sum()))
            # every input each frame carries, frame by frame, by index (as the per-frame engine)
            rows, cols = np.nonzero(has_u)
            self.router.inputs(nm.node, t_fr[rows], u_fr[rows, cols], cols.astype(np.int64))
        held_u = np.empty_like(u_fr)
        seen = np.ones(len(fr), np.bool_)
        for a in range(m):
            v, s = held_column(has_u[:, a], u_fr[:, a], float(nm.u[a]), bool(nm.u_seen[a]))
            held_u[:, a] = v
            seen &= s
        tr = dec.truth[fr]
        has_t = ~np.isnan(tr)
        if has_t.any():
            cnt.inc(C.SAMPLES_TRUTH, int(has_t.sum()))
        held_t, got_t = held_column(has_t, tr, nm.truth, nm.has_truth)
        n_out = np.array([len(r.outputs) for r in self.table.routes], np.int64)
        is_out = n_out[ra] > 0
        oi = np.flatnonzero(is_out)
        # everything held at this chunk's end, and at every frame (for ticks)
        prev_u = nm.u.copy()
        g0, r0 = nm.gamma.copy(), nm.rules
        if len(fr):
            nm.u[:] = held_u[-1]
            nm.u_seen |= has_u.any(axis=0)
            nm.truth = float(held_t[-1])
            nm.has_truth = bool(got_t[-1])
        t_o = t_fr[oi]
        status = np.zeros(len(oi), np.int64)
        kk = np.ones(len(oi), np.int64)
        restart = np.zeros(len(oi), np.bool_)
        jitter = np.zeros(len(oi), np.bool_)
        cand = wrap_all[fr[oi]]
        # the node's drive operational again (a row of this chunk): at its next sample
        resume = np.zeros(len(oi), np.bool_)
        resumed = self.resume_rows.get(nm.node)
        late = False
        if resumed is not None and len(resumed):
            at = np.searchsorted(fr[oi], resumed, side="left")
            resume[at[at < len(oi)]] = True
            late = bool((at >= len(oi)).any())
        rate_change = np.zeros(len(oi), np.int64)
        K.admit(t_o, lost_all[fr[oi]], cand, seen[oi], resume, nm.admission, cfg.rate,
                cfg.max_gap_s, cfg.silence_timeout_s, cfg.jitter_fraction, status, kk, restart,
                jitter, rate_change)
        for j in np.flatnonzero(rate_change).tolist():
            counter, event = admission.rate_event(float(t_o[j]), nm.node, int(rate_change[j]),
                                                  cfg.rate)
            if counter is not None:
                cnt.inc(counter)
                self._warn(f"rate-{nm.node}", event.text)
            events.append((2 * int(fr[oi[j]]), order, len(events), event))
        if late:
            nm.admission[admission.RESUME] = 1.0
        if cand.any():
            n_rep = int((status[cand] == admission.REPEATED).sum())
            n_wrap = int(cand.sum()) - n_rep
            if n_rep:
                cnt.inc(C.E2E_REPEATED, n_rep)
                self._warn("repeat", f"repeated alive counters: {n_rep} frames")
            if n_wrap:
                cnt.inc(C.E2E_COUNTER_JUMPS, n_wrap)
                cnt.inc(C.E2E_LOST_FRAMES, admission.WRAP_LOST * n_wrap)
        for code, name in admission.REFUSED.items():
            k_refused = int((status == code).sum())
            if k_refused:
                cnt.inc(name, k_refused)
        if jitter.any():
            cnt.inc(C.TIME_JITTER, int(jitter.sum()))
        A = np.flatnonzero(status == 0)
        oA = oi[A]
        kA = kk[A]
        rA = restart[A]
        if rA.any():
            cnt.inc(C.ESTIMATOR_RESTARTS, int(rA.sum()))
        pt = kA[~rA] - 1
        if (pt > 0).any():
            cnt.inc(C.SAMPLES_PREDICTED_THROUGH, int(pt[pt > 0].sum()))
        H = held_u[oA]
        U, nm.u_past = delayed(H, cfg.input_delay, nm.u_past, rA)
        Y = np.nan_to_num(dec.y[fr[oA]], nan=0.0)
        dts: NDArray[np.float64] = (kA * nm.T).astype(np.float64)
        nA = len(A)
        gam = np.zeros((nA, m))
        yest = np.zeros((nA, self.model.p))  # every output, for the samples file
        nis = np.zeros(nA)
        rules = np.zeros(nA, np.int64)
        isnan = np.zeros(nA, np.bool_)
        i = 0
        n_events = 0
        while i < nA:
            if rA[i]:
                nm.restart()
            nxt = np.flatnonzero(rA[i + 1:])
            end = i + 1 + int(nxt[0]) if len(nxt) else nA
            res = nm.est.step_many(U[i:end], Y[i:end], dts[i:end])
            j = i + res.count
            gam[i:j] = res.gamma[:res.count]
            yest[i:j] = res.y_est[:res.count]
            nis[i:j] = res.nis[:res.count]
            rules[i:j] = res.rules[:res.count]
            n_events += int(res.structure_event[:res.count].sum())
            nm.gamma = gam[j - 1].copy()
            nm.rules = int(rules[j - 1])
            if res.stopped_on_nan:
                isnan[j - 1] = True
                nm.restart()
            i = j
        nm.samples += nA
        if nA:
            cnt.inc(C.SAMPLES_ESTIMATED, nA)
        if isnan.any():
            cnt.inc(C.ESTIMATOR_NAN, int(isnan.sum()))
        if n_events:
            cnt.inc(C.ESTIMATOR_STRUCTURE_EVENTS, n_events)
        gmax = gam.max(axis=1) if nA else np.zeros(0)
        # samples and ticks in bus order: a tick follows the feed of its frame
        pos_s = fr[oA]
        tk = tick_idx[tick_idx >= created] if created >= 0 else tick_idx
        keys = np.concatenate([2 * pos_s, 2 * tk + 1])
        order_k = np.argsort(keys, kind="stable")
        is_tick = np.concatenate([np.zeros(nA, np.bool_), np.ones(len(tk), np.bool_)])[order_k]
        tt = np.concatenate([c.t[pos_s], c.t[tk]])[order_k]
        gg = np.concatenate([gmax, np.zeros(len(tk))])[order_k]
        ni = np.concatenate([nis, np.zeros(len(tk))])[order_k]
        rb = np.concatenate([rA, np.zeros(len(tk), np.bool_)])[order_k]
        nn = np.concatenate([isnan, np.zeros(len(tk), np.bool_)])[order_k]
        L = len(keys)
        st_out = np.zeros(L, np.int64)
        ev = np.zeros(L, np.int64)
        prev = np.zeros(L, np.int64)
        cause = np.zeros(L, np.int64)
        fev = np.zeros(L, np.int64)
        flag = np.zeros(L, np.bool_)
        counts = np.zeros(2, np.int64)
        K.classify(is_tick, tt, gg, ni, rb, nn, nm.diag, self.cls_prm, st_out, ev, prev,
                   cause, fev, flag, counts)
        if counts[0]:
            cnt.inc(C.NODES_MODEL_MISMATCH, int(counts[0]))
        if counts[1]:
            cnt.inc(C.NODES_SILENT, int(counts[1]))
        # samples to the sinks, as columns
        sample_of = order_k[~is_tick]  # item -> sample index, in order
        st_sample = np.zeros(nA, np.int64)
        st_sample[sample_of] = st_out[~is_tick]
        mm_sample = np.zeros(nA, np.bool_)
        mm_sample[sample_of] = flag[~is_tick]
        good = ~isnan
        if good.any():
            self.router.samples(nm.node, SampleColumns(
                t=c.t[pos_s][good], measured=Y[good, 0], estimated=yest[good, 0],
                gamma=gmax[good], rules=rules[good], state=st_sample[good], nis=nis[good],
                true_gamma=np.where(got_t[oA], held_t[oA], np.nan)[good],
                model_mismatch=mm_sample[good],
                inputs=U[good], outputs=Y[good], predicted=yest[good], gammas=gam[good]))
        # transitions and due diagnoses
        if not self.router.wants_diagnosis:
            ev[ev == 2] = 0
        if not ev.any():
            return
        sample_idx = np.full(L, -1, np.int64)
        sample_idx[~is_tick] = sample_of
        last_sample = np.maximum.accumulate(np.where(~is_tick, np.arange(L), -1))
        tick_keys = keys[order_k]
        for item in np.flatnonzero(ev).tolist():
            if not is_tick[item]:
                s_i = int(sample_idx[item])
                g_vec, rl, u_vec = gam[s_i], int(rules[s_i]), H[s_i]
            else:
                ls = int(last_sample[item])
                if ls >= 0:
                    s_i = int(sample_idx[ls])
                    if isnan[s_i]:  # restarted after it
                        g_vec, rl = np.zeros(m), self._fresh_rules
                    else:
                        g_vec, rl = gam[s_i], int(rules[s_i])
                else:
                    g_vec, rl = g0, r0
                fpos = int(tick_keys[item] // 2)
                k_fr = int(np.searchsorted(fr, fpos, side="right")) - 1
                u_vec = held_u[k_fr] if k_fr >= 0 else prev_u
            j = int(np.argmax(g_vec))
            g = float(g_vec.max())
            fv = float(g_vec[j] * u_vec[j])
            t_ev = float(tt[item])
            state = _STATES[int(st_out[item])]
            p_state = _STATES[int(prev[item])]
            mm = bool(flag[item])
            key = int(tick_keys[item])
            if fev[item]:  # the flag's event first (`MonitorPipeline._report`)
                events.append((key, order, len(events), DiagnosisEvent(
                    t=t_ev, node=nm.node, state=p_state.label, previous=p_state.label,
                    gamma=g, fault_input=fv, rules=rl,
                    cause=FLAG_CAUSES[int(fev[item]) - 1],
                    model_mismatch=mm, kind=MODEL_MISMATCH)))
            if ev[item] == 1 and state != p_state:
                why = HEALTH_CAUSES[int(cause[item])]
                events.append((key, order, len(events), DiagnosisEvent(
                    t=t_ev, node=nm.node, state=state.label, previous=p_state.label, gamma=g,
                    fault_input=fv, rules=rl, cause=why, model_mismatch=mm)))
            if self.router.wants_diagnosis:
                events.append((key, order, len(events),
                               Diagnosis(nm.node, t_ev, state, g, fv, rl, mm)))

    @functools.cached_property
    def _fresh_rules(self) -> int:
        return FuzzyUKF(self.model, self.cfg.estimator).out.rules

    def result(self, path: Path | None) -> ReplayResult:
        nodes = {n: {"state": _STATES[int(nm.diag[REPORTED])].label,
                     "model_mismatch": bool(nm.diag[FLAGGED] != 0.0),
                     "gamma": float(nm.gamma.max()),
                     "rules": nm.rules, "samples": nm.samples}
                 for n, nm in sorted(self.nodes.items())}
        return ReplayResult(path, self.offset, dict(sorted(self.counters.items())),
                            list(self.events), nodes)


def columnar_obstacle(db: Any, cfg: MonitorConfig | None = None) -> str | None:
    """Why logs of this decoder cannot be replayed in columns (SecOC, a codec or frames
    this path has no decoder for), or None when they can; `replay_file` would fall back to
    the per-frame path for the reason given."""
    model = (cfg or MonitorConfig()).plant().discretize(1.0 / (cfg or MonitorConfig()).rate)
    try:
        RouteTable.of(db, model.m, model.p)
    except NotColumnar as exc:
        return str(exc)
    return None


def replay_chunks(chunks: Iterable[FrameChunk], db: Any, cfg: MonitorConfig | None = None,
                  sink: Sink | None = None) -> ReplayResult:
    """`replay_file` on chunks already in memory (no fallback: `NotColumnar` is raised)."""
    rp = _Replay(db, cfg or MonitorConfig(), sink if sink is not None else Sink())
    for c in chunks:
        rp.chunk(c)
    return rp.result(None)


def replay_file(path: str | Path, db: Any, cfg: MonitorConfig | None = None,
                sink: Sink | None = None, *, chunk_frames: int = DEFAULT_CHUNK_FRAMES
                ) -> ReplayResult:
    """Replay the bus log at `path` (any of `monitor.bus.logfile.LOG_FORMATS`) through
    decode, estimation and diagnosis, a chunk of `chunk_frames` frames at a time, into `sink`.

    `db` is the rig's frame decoder (`MotorDatabase` or `RigCodec`, as
    `monitor.rig.build_decoder` makes it), `cfg` the monitor's configuration. Gives the
    per-frame path's events and counters. A file this path cannot take (SecOC: per-frame
    freshness state) goes through the per-frame path instead, said in one log line and in
    `ReplayResult.fallback`. Raises `monitor.columnar.reader.LogReadError` (a
    `MonitorError`) for a file that cannot be read. Does not close `sink`.
    """
    p = Path(path)
    cfg = cfg or MonitorConfig()
    the_sink = sink if sink is not None else Sink()
    try:
        rp = _Replay(db, cfg, the_sink)
    except NotColumnar as exc:
        log.warning("columnar replay: %s: %s; replaying it frame by frame", p, exc)
        return _per_frame(p, db, cfg, the_sink, str(exc))
    for c in read_chunks(p, chunk_frames):
        rp.chunk(c)
        del c
        release_free_heap()
    return rp.result(p)


_LIBC_TRIM: Callable[[int], int] | None = None
with suppress(OSError, AttributeError):  # glibc only (musl, macOS: nothing to do)
    _LIBC_TRIM = ctypes.CDLL(None).malloc_trim


def release_free_heap() -> None:
    """Give the pages of freed memory back to the system (glibc's ``malloc_trim``).

    Every chunk allocates and frees tens of MB of arrays (the reader's columns, the decoded
    signals, Rerun's Arrow copies). glibc's allocator keeps most of what is freed in its
    heaps; in a long replay, fragmentation then let the resident memory creep up by ~1 MB per
    10^6 frames though nothing was held (measured over 3*10^7 frames: with a trim after each
    chunk it stays flat). A trim costs about a millisecond against ~0.5 s of a chunk."""
    if _LIBC_TRIM is not None:
        _LIBC_TRIM(0)


def _per_frame(path: Path, db: Any, cfg: MonitorConfig, sink: Sink, why: str) -> ReplayResult:
    from monitor.pipeline import MonitorPipeline

    events: list[DiagnosisEvent] = []

    class _Keep(Sink):
        def on_transition(self, event: DiagnosisEvent) -> None:
            events.append(event)

    from monitor.sinks.base import FanOut

    pipe = MonitorPipeline(db, cfg, sink=FanOut([sink, _Keep()]))
    n = _feed(pipe, path)
    s = pipe.summary()
    return ReplayResult(path, n, dict(pipe.counters), events, s["nodes"], columnar=False,
                        fallback=why)


def _feed(pipe: Any, path: Path) -> int:
    """`monitor.pipeline.feed.replay_frames`: `feed_log` of `read_log(path)`, python-can's
    reader, exactly the per-frame path."""
    return int(replay_frames(pipe, path))
