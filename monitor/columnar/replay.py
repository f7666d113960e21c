"""`ColumnarEngine`: the monitor's rules over a chunk of frames at a time, on a
`MonitorPipeline`'s state; `replay_file`: one bus log through it a chunk at a time.

A replay gives what ``feed_log(MonitorPipeline(db, cfg, sink=sink), read_log(path))`` gives:
the same diagnosis events, counters and samples (see the package docstring for what differs:
only when counter snapshots reach the sink).
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

from monitor.bus.cia402 import IGNORED_NOT_OPERATIONAL, IGNORED_PROTOCOL
from monitor.columnar import kernels as K
from monitor.columnar.decode import REASONS, DecodedChunk, NotColumnar, RouteTable
from monitor.columnar.reader import DEFAULT_CHUNK_FRAMES, FrameChunk, read_chunks
from monitor.columnar.sinks import SinkRouter
from monitor.diagnosis import HealthState
from monitor.diagnosis.rules import FLAG_CAUSES, HEALTH_CAUSES
from monitor.estimation.fuzzy_ukf import FuzzyUKF
from monitor.pipeline import MonitorConfig, MonitorPipeline, NodeMonitor, admission
from monitor.pipeline import counters as C
from monitor.pipeline.admission import DROP, NO_COUNTER
from monitor.pipeline.events import (
    HEALTH,
    MODEL_MISMATCH,
    Diagnosis,
    DiagnosisEvent,
    SampleColumns,
)
from monitor.pipeline.feed import replay_frames
from monitor.pipeline.samples import delayed, held_column, held_columns
from monitor.sinks.base import FanOut, Sink

__all__ = ["ColumnarEngine", "ReplayResult", "columnar_obstacle", "replay_chunks", "replay_file"]

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


class ColumnarEngine:
    """The monitor's rules over a chunk of frames at a time, on the state of a
    `MonitorPipeline`: its nodes (`NodeMonitor`: estimator, held inputs, admission and
    diagnosis state), counters, alive-counter tracker, CANopen drives, warnings and sink.

    Feeding a chunk here or its frames one by one to `pipe.feed` (with `feed_log`'s ticks)
    gives the same events, samples and counters, so the two can be mixed on one pipeline:
    the live daemon hands a socket's backlog to `chunk` and single frames to `feed`.
    `ticks`: check the timeouts every `TICK_S` of the frames' time stamps inside a chunk,
    as `feed_log` does, and hand the counters to the sink after every chunk (a replay);
    False where the caller ticks (the live loop), the counters then going to the sink at the
    per-frame engine's pace (`MonitorPipeline.counters_due`).
    Raises `NotColumnar` for a codec whose frames must go one by one (SecOC).
    """

    def __init__(self, pipe: MonitorPipeline, *, ticks: bool = True) -> None:
        self.pipe = pipe
        self.ticks = ticks
        cfg = self.cfg = pipe.cfg
        self.model = pipe.model
        self.table = RouteTable.of(pipe.db, self.model.m, self.model.p)
        self.secoc = bool(getattr(pipe.db, "secoc_enabled", False))
        self.router = SinkRouter(pipe.sink)
        self.counters = pipe.counters
        self.nodes = pipe.nodes
        self.cls_prm = pipe.diag_prm
        routes = self.table.routes
        self.stream_of = np.array(self.table.route_stream or [0], np.int64)
        self.output_only = np.array([bool(r.outputs) and not r.inputs and r.truth is None
                                     for r in routes] or [False])
        self.n_out = np.array([len(r.outputs) for r in routes] or [0], np.int64)
        self.route_node = np.array([r.node for r in routes] or [0], np.int64)
        not_read = [admission.not_read(r.kind, r.node, cfg.nodes, self.secoc) for r in routes]
        self.skip_names = sorted({x for x in not_read if x is not None})
        self.route_skip = np.array([0 if x is None else 1 + self.skip_names.index(x)
                                    for x in not_read] or [0], np.int64)
        self.drives = pipe.drives  # a CANopen rig's drives, as the per-frame engine
        self.held = pipe.held  # nodes whose drive said it was not operational
        self.resume_rows: dict[int, NDArray[np.int64]] = {}  # this chunk's resumptions
        self.last_tick = np.array([-math.inf])
        self.offset = 0

    def _node(self, n: int) -> NodeMonitor:
        return self.pipe.node(n)

    def _warn(self, key: str, text: str) -> None:
        self.pipe.warn.warn(key, text)

    # ------------------------------------------------------------------------------ chunk

    def chunk(self, c: FrameChunk) -> None:
        n = len(c)
        if n == 0:
            return
        cnt = self.counters
        cnt.received(n, int(c.is_fd.sum()), int((c.is_fd & c.is_esi).sum()))
        events: list[tuple[int, int, int, Any]] = []  # (key, node order, seq, event)
        for i in np.flatnonzero(c.error).tolist():
            event = self.pipe.error_frame(c.message(i))
            events.append((2 * i, -1, len(events), event))  # keys: rows of this chunk
        dec = self.table.decode(c)
        tick_idx = np.zeros(n, np.int64)  # the frames after which `feed_log` ticks
        nt = K.ticks(c.t, self.last_tick, tick_idx, K.TICK_S) if self.ticks else 0
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
                    events.append((key, -1, len(events), self.pipe.drive_report(r)))
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
            tracker = self.pipe.tracker  # the per-frame engine's, so either may go next
            alive_last = np.array(tracker.last(self.table.streams) or [-1], np.int64)
            K.alive(self.stream_of[rc], dec.counter[ci], self.output_only[rc], alive_last,
                    lz, wz)
            tracker.remember(self.table.streams, alive_last[:len(self.table.streams)].tolist())
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
                self.pipe.sink.on_transition(ev)
            elif isinstance(ev, Diagnosis):
                self.pipe.sink.on_diagnosis(ev)
            else:
                self.pipe.sink.on_bus_event(ev)
        t_end = float(c.t[-1])
        if self.ticks or self.pipe.counters_due(t_end):  # live: at the per-frame pace
            self.pipe.emit_counters(t_end)

    def _node_chunk(self, nm: NodeMonitor, c: FrameChunk, dec: DecodedChunk, fr: NDArray[np.int64],
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
        # what an output in each frame holds (rule 1), and the latest inputs after each frame
        prev_u = nm.held.latest.copy()
        at_u, seen, held_u = held_columns(has_u, u_fr, t_fr, nm.held, nm.window)
        tr = dec.truth[fr]
        has_t = ~np.isnan(tr)
        if has_t.any():
            cnt.inc(C.SAMPLES_TRUTH, int(has_t.sum()))
        truth = nm.truth_gamma
        held_t, got_t = held_column(has_t, tr, math.nan if truth is None else truth,
                                    truth is not None)
        is_out = self.n_out[ra] > 0
        oi = np.flatnonzero(is_out)
        # the truth held at this chunk's end (the inputs: `held_columns`)
        g0, r0 = nm.estimator.out.gamma.copy(), nm.estimator.out.rules
        if len(fr):
            nm.truth_gamma = float(held_t[-1]) if got_t[-1] else None
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
            event = self.pipe.rate_change(float(t_o[j]), nm.node, int(rate_change[j]))
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
        H = held_u[oA]  # the latest inputs at each sample (the fault's input, as live)
        U, nm.u_past = delayed(at_u[oA], cfg.input_delay, nm.u_past, rA)
        Y = np.nan_to_num(dec.y[fr[oA]], nan=0.0)
        dts: NDArray[np.float64] = (kA * nm.T).astype(np.float64)
        nA = len(A)
        gam = np.zeros((nA, m))
        gsd = np.zeros((nA, m))
        yest = np.zeros((nA, self.model.p))  # every output, for the samples file
        onoise = np.zeros((nA, self.model.p))
        pnoise = np.zeros(nA)
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
            res = nm.estimator.step_many(U[i:end], Y[i:end], dts[i:end])
            j = i + res.count
            gam[i:j] = res.gamma[:res.count]
            gsd[i:j] = res.gamma_sd[:res.count]
            yest[i:j] = res.y_est[:res.count]
            onoise[i:j] = res.output_noise[:res.count]
            pnoise[i:j] = res.process_noise[:res.count]
            nis[i:j] = res.nis[:res.count]
            rules[i:j] = res.rules[:res.count]
            n_events += int(res.structure_event[:res.count].sum())
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
        worst = gam.argmax(axis=1) if nA else np.zeros(0, np.int64)
        gmax = gam[np.arange(nA), worst]
        gmax_sd = gsd[np.arange(nA), worst]  # of the gamma^ the diagnosis reads
        # samples and ticks in bus order: a tick follows the feed of its frame
        pos_s = fr[oA]
        tk = tick_idx[tick_idx >= created] if created >= 0 else tick_idx
        keys = np.concatenate([2 * pos_s, 2 * tk + 1])
        order_k = np.argsort(keys, kind="stable")
        is_tick = np.concatenate([np.zeros(nA, np.bool_), np.ones(len(tk), np.bool_)])[order_k]
        tt = np.concatenate([c.t[pos_s], c.t[tk]])[order_k]
        gg = np.concatenate([gmax, np.zeros(len(tk))])[order_k]
        gs = np.concatenate([gmax_sd, np.zeros(len(tk))])[order_k]
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
        diag = nm.diag  # an array, or a list where the JIT is off (`rules.step_vectors`)
        diag_a = diag if isinstance(diag, np.ndarray) else np.array(diag, np.float64)
        K.classify(is_tick, tt, gg, gs, ni, rb, nn, diag_a, self.cls_prm, st_out, ev, prev,
                   cause, fev, flag, counts)
        if diag_a is not diag:
            for k_s, v_s in enumerate(diag_a.tolist()):
                diag[k_s] = v_s
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
                inputs=U[good], outputs=Y[good], predicted=yest[good], gammas=gam[good],
                gamma_sd=gmax_sd[good], output_noise=onoise[good],
                process_noise=pnoise[good]))
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


class _Transitions(Sink):
    """Keeps every `DiagnosisEvent` for the `ReplayResult`."""

    def __init__(self) -> None:
        self.events: list[DiagnosisEvent] = []

    def on_transition(self, event: DiagnosisEvent) -> None:
        self.events.append(event)


def _pipeline(db: Any, cfg: MonitorConfig | None, sink: Sink | None
              ) -> tuple[MonitorPipeline, _Transitions]:
    keep = _Transitions()
    sinks = [keep] if sink is None else [sink, keep]
    return MonitorPipeline(db, cfg or MonitorConfig(), sink=FanOut(sinks)), keep


def _result(path: Path | None, frames: int, pipe: MonitorPipeline, keep: _Transitions,
            fallback: str | None = None) -> ReplayResult:
    s = pipe.summary()
    return ReplayResult(path, frames, s["counters"], keep.events, s["nodes"],
                        columnar=fallback is None, fallback=fallback)


def replay_chunks(chunks: Iterable[FrameChunk], db: Any, cfg: MonitorConfig | None = None,
                  sink: Sink | None = None) -> ReplayResult:
    """`replay_file` on chunks already in memory (no fallback: `NotColumnar` is raised)."""
    pipe, keep = _pipeline(db, cfg, sink)
    engine = ColumnarEngine(pipe)
    for c in chunks:
        engine.chunk(c)
    return _result(None, engine.offset, pipe, keep)


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
    pipe, keep = _pipeline(db, cfg, sink)
    try:
        engine = ColumnarEngine(pipe)
    except NotColumnar as exc:
        log.warning("columnar replay: %s: %s; replaying it frame by frame", p, exc)
        return _result(p, replay_frames(pipe, p), pipe, keep, str(exc))
    for c in read_chunks(p, chunk_frames):
        engine.chunk(c)
        del c
        release_free_heap()
    return _result(p, engine.offset, pipe, keep)


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
