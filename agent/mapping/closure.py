"""Loop closure: the mapper's keyframes as a pose graph, closures found and verified, the graph solved.

The front end (``mapper.py``) matches each scan against the recent map; alone it drifts, and a robot
that comes back to a room draws it again where its drifted pose says. ``LoopCloser`` keeps what a
closure needs (after Cartographer's global SLAM, Hess et al. 2016, on a smaller scale):

- **Nodes**: the mapper's spaced keyframes (0.3 m / 10 deg apart), each with its scan in the sensor
  frame. Consecutive nodes are joined by the front end's relative pose (a step edge whose
  uncertainty grows with the step, and is larger along a direction the front end's match left
  ill-posed: down a corridor, ``step_degenerate_ratio``).
- **Submaps**: every ``submap_nodes`` consecutive nodes, drawn (once, when a closure check first
  needs it) into a small log-odds grid and a point-to-line map in the frame of their first node.
- **Search**: each new node is tried against at most ``attempts_per_node`` finished submaps whose
  nodes lie within ``search_radius`` of it and that are at least ``min_gap_nodes`` behind (the front
  end already matched the recent ones), nearest first, skipping those tried within
  ``retry_nodes``; a bounded rate, so an agent's CPU share stays flat however long it maps.
- **Verification**: correlative search of the node's scan over the submap's grid in a wide window
  (``search_xy``, ``search_theta``, the motion prior nearly flat), then point-to-line refinement
  against the submap's points. Accepted when the field score is at least ``min_score``, at least
  ``min_inlier_ratio`` of the points found a line within 0.1 m, the two answers agree within
  ``max_disagreement`` and the refined pose is constrained in every direction (``min_weak``: a
  corridor seen end-on fixes no position along it); one that moves its node far also needs most of
  its inliers on walls seen from the side it sees them from (``min_facing_share``).
- **Solve**: accepted closures join the graph; it is optimised at once (Gauss-Newton, sparse), then
  every closure whose error is above ``max_chi2`` (e^T Omega e, 3 degrees of freedom) is dropped and
  the graph solved again: a verified but wrong closure is rejected, a right one absorbed. A wrong
  one the chain absorbs instead, each step bent a little, is found by what it conflicts with: the
  groups of closures that were large corrections, weighed in pairs once complete, the chi2 each
  removal lowers (``conflict_pair_chi2``; again before the final pass, ``conflict_chi2``).
- **Final pass** (a replay's end, ``finish``): every node matched again against the submaps it sees,
  in a small window around the solved graph, and against nearby nodes' scans; these edges replace the
  online closures, which only had to bring the graph that near. The log's odometry joins it too, each
  step's translation an edge at the sd the log's own steps show (``final_odometry_margin``).

The caller (the mapper) re-renders its grid from the optimised node poses. numpy and scipy (the
solve); time is an argument; no I/O.

**In line or elsewhere.** ``close()`` searches and solves in line (a replay). On a robot the search
runs elsewhere (a worker thread: agent/mapping/worker.py): ``plan(k, t)`` hands out a node's
verifications as ``Check`` values that carry everything they need (the scan, the submap drawn or the
scans to draw it from, the window), ``run_check`` runs one anywhere, and ``take(results)`` brings the
verdicts back into the graph (confirmation of large corrections, the solve) in the owner's thread.
``check_period`` bounds the rate of fresh searches in time (a node's search waits that long after
the last one), so the search costs at most so much per second however fast nodes come.
"""

from __future__ import annotations

import bisect
import copy
import itertools
import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np
import numpy.typing as npt

from fleetlink.agent.mapping.bnb import PrecomputedGrids, search
from fleetlink.agent.mapping.grid import GridConfig, LogOddsGrid
from fleetlink.agent.mapping.matcher import (
    IcpResult,
    LocalMap,
    _refine,
    _refine_many,
    field_score,
    icp_refine,
    icp_refine_many,
)
from fleetlink.agent.mapping.posegraph import PoseGraph
from fleetlink.agent.mapping.scan import surface_fill
from fleetlink.shared.se2 import Pose, compose, inverse, relative, wrap

__all__ = [
    "Check",
    "CheckResult",
    "CloserConfig",
    "CloserStats",
    "Closure",
    "ClosureSearch",
    "DeferredSearch",
    "Drawn",
    "LoopCloser",
    "NodeScan",
    "degenerate_direction",
    "replay_closer",
    "run_check",
]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class CloserConfig:
    submap_nodes: int = 10  # consecutive nodes per submap (~3 m of travel)
    search_radius: float = 2.5  # m: a submap with a node this near the new node is a candidate
    min_gap_nodes: int = 30  # candidates end at least this many nodes back
    attempts_per_node: int = 1  # closure checks per new node (the rate bound)
    retry_nodes: int = 5  # a submap tried is not tried again for this many nodes
    search_xy: float = 1.0  # m, half-width of the verification's translation window
    search_theta: float = math.radians(20.0)
    # Each candidate submap searched in a window of its own, grown by the drift over the graph's shortest
    # path between it and the node (``LoopCloser._candidates``), not by the path since the last closure;
    # off by default (``long_loops`` turns it on, with three checks a node): on the offices' published
    # relations it moved one ambiguous revisit past 0.20 m (aces 0.180 -> 0.226 m).
    window_per_submap: bool = False
    # Without it, a candidate submap at least ``far_loop_m`` from the node along the graph (``_drift``:
    # a return after a loop that long, however recently the robot closed onto its own loop) is still
    # searched in a window of its own, up to ``far_loop_checks`` of them a node besides the nearest
    # candidate (0: never). The one window shrinks at every closure: MIT's Killian Court came back after
    # loops of 300 m and more 15-19 m from the corridors it had mapped, with windows of 12-18 m. aces'
    # candidates lie at most 159 m along the graph, the corrected csail's 204 m; intel, aces, fr079 and
    # mit-csail (published and corrected) map the same with it to the bit. A far loop's check changes
    # the map only through a closure it finds (its mark, pace and drawings are its own: ``_fresh_checks``);
    # from 130 m Killian maps the same as from 250 m, with more checks.
    far_loop_m: float = 250.0
    far_loop_checks: int = 2
    # The pose drifts while no closure holds it: both the radius and the window grow by this share of
    # the path travelled since the last accepted closure or site prior (and the heading window by
    # drift_theta per metre), up to the caps.
    drift_rate: float = 0.1
    drift_theta_per_m: float = math.radians(0.5)
    max_search_xy: float = 10.0  # m
    max_search_theta: float = math.radians(35.0)
    # Where the nodes carry the odometry's own poses (``add_node``'s ``odometry``: a replay), the growth
    # is held to ``odometry_gain`` x how far the front end has moved from the odometry since the last
    # closure (at least ``odometry_floor`` / ``odometry_theta_floor`` per metre travelled; 0: off). Two
    # independent sensors that agree say the map has not drifted far, so a look-alike metres away is
    # not searched: MIT's infinite corridor on its own poses (the front end 0.9 m from them after 160
    # m) had nodes matched 6.5 m off, doorways two periods along, in a 10 m window. Where they disagree
    # the window may grow to ``odometry_max_search_xy``: the corridor's 330 m loop comes back 10-20 m
    # off, beyond ``max_search_xy`` (complete relations 3.42 -> 0.06 m).
    odometry_gain: float = 3.0
    odometry_floor: float = 0.02
    odometry_theta_floor: float = math.radians(0.03)
    odometry_max_search_xy: float = 30.0  # m
    min_score: float = 0.5  # mean likelihood-field value of the scan's points on the submap, refined
    search_min_score: float = 0.4  # the branch-and-bound's floor (on the lattice)
    # A submap that saw its walls far off is drawn with each scan's surfaces filled between
    # neighbouring hits (``scan.surface_fill``: endpoints under ``fill_max_gap`` m apart, ranges within
    # ``fill_depth_share`` x range + ``fill_depth_m``; 0: never). Beams 1 degree apart leave a wall
    # 10 m off a dotted line 0.17 m a dot, wider than the field's blur: a node scored 0.55 on its own
    # submap in the Acapulco convention hall (intel 0.76) and no closure passed there; filled, 0.80.
    fill_max_gap: float = 0.5
    # ... when its scans saw their walls at least this far off (the median over its scans of each
    # scan's median hit range; 0: every submap). Offices sit at 2 m (intel, aces, MIT's corridors), the
    # hall at 8 m, the campus at 13 m. Filled, every score rises, a look-alike's too: filling the offices'
    # submaps as well cost aces' published worst revisit 0.180 -> 0.188-0.232 m and broke the infinite
    # corridor unless large corrections scored more (``open_space`` does both).
    fill_from_range: float = 5.0
    fill_depth_share: float = 0.05
    fill_depth_m: float = 0.1
    angle_step: float = math.radians(0.5)  # the branch-and-bound's rotations
    min_inlier_ratio: float = 0.6
    inlier_distance: float = 0.1  # m
    # A match that moves its node more than ``confirm_above`` needs at least this share of its inliers
    # on submap points seen from the side this scan sees them from (their normals face this sensor).
    # A field match cannot tell a wall's sides apart: on a ring corridor round a block, the block's
    # corner seen from inside it fits the outer walls' corner 2 m off, every inlier matched from
    # behind. Small corrections are exempt: true matches across thin partitions (intel's office) have
    # most of their inliers on the partition's far side, 5 cm away.
    min_facing_share: float = 0.5
    max_disagreement: float = 0.1  # m between the correlative and the refined answer
    max_disagreement_angle: float = math.radians(2.0)
    min_weak: float = 10000.0  # smallest eigenvalue of the refinement's information (1/m^2)
    step_sigma_xy: float = 0.01  # m, the front end's step: sd = base + per metre moved
    step_sigma_xy_per_m: float = 0.03
    step_sigma_theta: float = math.radians(0.3)
    step_sigma_theta_per_rad: float = 0.02
    # A front-end step whose match was ill-posed along a direction (the xy information's eigenvalues more
    # than ``step_degenerate_ratio`` apart: a corridor) is held only loosely along it, sd base + this per
    # metre (what the odometry seed is worth there), so the final pass's edges can move it (0: off).
    step_degenerate_ratio: float = 20.0
    step_degenerate_sigma_per_m: float = 0.1
    closure_sigma_xy: float = 0.03  # m
    closure_sigma_theta: float = math.radians(1.0)
    max_chi2: float = 16.0  # a closure whose error after the solve is above this is dropped
    prior_solve_nodes: int = 20  # with site priors, solve at least every this many nodes
    max_drops: int = 3  # closures dropped per solve at most (each costs a solve)
    iterations: int = 10
    confirm_above: float = 0.5  # m: a closure moving its node more than this waits for a second one
    # ... and is refused outright where the node's scan also fits the submap nearer where the graph
    # puts it (searched within half the correction of the guess, something there passes the gates,
    # away from the first answer): two answers are a look-alike, as in the final pass
    # (``final_ambiguity_jump``). MIT's infinite corridor (its corrected log on its own poses):
    # doorways every few metres; nodes 297 and 302 both matched two periods (7 m) along and confirmed
    # each other where the graph's guess was right, and the map broke (7.2 m mean).
    large_unique: bool = True
    # ... and a fresh search's correction larger than ``confirm_above`` on a filled submap must score at
    # least this (the refined field score; Cartographer likewise asks more of a global match, 0.6, than
    # of a local one, 0.55). Filled submaps lift every score: MIT's infinite corridor, every submap
    # filled, took a doorway 7 m along at 0.60, confirmed by the next node at 0.58 (complete relations
    # 0.06 -> 0.16 m); the true large closures there and on the other logs scored 0.63 and up. Asked of
    # unfilled submaps too, 0.55-0.6 cost aces' published worst revisit 0.185 -> 0.201 m.
    large_min_score: float = 0.62
    # ... and on an unfilled submap at least this, a little above ``min_score``: MIT's Killian Court
    # took a look-alike 3.6 m along a corridor at 0.507 (node 347 onto submap 160, then confirmed by
    # the next node), about 110 of its relations 4 m off (0.254 -> 0.115 m without it); its true large
    # closures and the other logs' scored 0.53 and up. 0.55 turned one of the Freiburg hospital's
    # returns away (0.86 -> 1.66 m).
    large_min_score_unfilled: float = 0.52
    confirm_nodes: int = 10  # ... within this many nodes
    # ... from a node at least this far from the first one's, or turned this much: a node nearer sees
    # much what the first saw and agrees with a look-alike as readily (the published MIT CSAIL log:
    # nodes 522 and 523, 0.4 m apart, both matched 1.57 m along one long wall, confirmed each other:
    # revisits 1.45 m off). Scans of the corrected logs are 0.5-1 m apart or turned ~30 deg: there the
    # next node still confirms (0: any later node may).
    confirm_apart_m: float = 0.5
    confirm_apart_rad: float = math.radians(20.0)
    # ... or, unturned, at least this share of the correction apart (m): a correction of metres asks as
    # much of its second opinion. Repeated rooms fool neighbouring views alike (the FHW museum's
    # corrected log: nodes 194 and 195, 0.8 m apart, both matched the partitions 10.8 m off and
    # confirmed each other; the map folded). A node turned as far sees other walls (aces: a 7.8 m
    # correction confirmed by a node 0.27 m on, turned 40 degrees).
    confirm_apart_share: float = 0.1
    confirm_distance: float = 0.2  # m: two closures agree when their corrections differ by less
    confirm_angle: float = math.radians(2.0)
    bnb_depth: int = 6  # branch-and-bound levels: the top blocks are 2^6 cells (3.2 m at 5 cm)
    # The final pass (``finish``, the end of a replay): every node matched against the finished submaps
    # near it (not its own), in a small window around where the solved graph puts it; each match an edge.
    final_radius: float = 3.0  # m: a submap seen from this near (2 m per radian of heading counted in)
    final_per_node: int = 6  # submaps per node at most, the nearest by view first
    # ... and besides them this many more, the nearest by distance alone (within ``final_radius``):
    # a submap mapped facing the other way, which the ranking by view leaves out, though a node passing
    # back down a corridor sees the same walls beside it (aces' worst revisits were such pairs).
    final_any_heading: int = 2
    # Not matched against a submap that starts or ends within this many nodes of the node: the node next
    # to a submap's first node measured against that submap is mostly their step again, the odometry
    # edge's own measurement, and held at the closure's sd it overrides a step held loosely down a corridor.
    final_min_gap_nodes: int = 1
    final_window_xy: float = 0.3  # m
    final_window_theta: float = math.radians(4.0)
    # A node no submap took within the final window is searched again this far (m; 0: not): a tail
    # that comes back to the start after the last online closure lies further off than the window
    # (the corrected belgioioso log's last scans, 0.5-1 m; orebro's, 1.2-1.4 m). The heading window
    # stays the final one: 10 degrees turned single scans of the csail log 8 degrees off their neighbours.
    final_wide_window_xy: float = 1.25
    # ... only against submaps at least this many nodes before or after the node (a loop closure's
    # search, as ``min_gap_nodes`` online; 0: any). The front end's chain ties a node to the submaps
    # beside it within centimetres, yet at 1 m the published aces log matched six nodes 0.8-1.2 m
    # along the corridor against the submap two to three nodes on, and at 1.25 m fifteen, which cost
    # it 0.0351 -> 0.0369 m.
    final_wide_min_gap_nodes: int = 30
    final_sigma_xy: float = 0.03  # m
    final_sigma_theta: float = math.radians(1.0)
    final_drops: int = 20  # edges the final solve may drop, one at a time
    # A final-pass match that fails only ``min_weak`` (a corridor: its strong direction passes) is kept
    # as a partial edge: sd ``final_partial_sigma`` along its weak direction, the usual across (0: off).
    final_partial_sigma: float = 0.5  # m
    # A final-pass match more than this (m) from the closed graph's guess is kept only if the guess is
    # not a match of its own (refined from there, it passes the gates at least this far from the first
    # answer): two answers in one window are a look-alike, not a correction (intel's corridors; 0: off).
    final_ambiguity_jump: float = 0.1
    # In the final solve, while a front-end step's error is above ``max_chi2`` and above every closure's,
    # that step is held loosely (sd ``step_sigma_xy`` + ``step_degenerate_sigma_per_m``
    # per metre, the heading 3x) before a closure is dropped: a step matched wrong but held tight makes
    # the right matches at its node look like the outliers (aces: a step 0.47 m off, held at 2.6 cm).
    final_loosen_steps: bool = True
    # Scan to scan (Lu and Milios' constraints, beside the submap matches): each node matched against
    # up to this many earlier nodes' own scans (0: off), at least ``final_pair_gap_nodes`` before it,
    # within ``final_pair_radius`` m and ``final_pair_turn`` rad, nearest by view first; kept when well
    # posed (``final_pair_weak``) with ``final_pair_inliers`` of its points on a line, within the final
    # window of the graph's guess. A submap carries any wrong step inside it into every match against
    # it; two scans carry none. Three, not four (thirty-eighth session): the published logs' means the
    # same or a little better (the hospital 0.904 -> 0.884 m), the final pass a sixth cheaper; two let
    # mit-csail's worst revisit go 0.226 -> 0.346 m.
    final_pair_per_node: int = 3
    final_pair_gap_nodes: int = 1
    final_pair_radius: float = 2.0
    final_pair_turn: float = math.radians(60.0)
    final_pair_weak: float = 10000.0
    # Share of the scan's points on a line of the other's: 0.25, not the checked set's 0.5 (intel seed
    # 5's scan 761 has ~50 of 180 there even from the reference, and no edge at all at 0.5).
    final_pair_inliers: float = 0.25
    # A pair the point-to-line refuses from the graph's guess, its nodes at most ``final_pair_search_nodes``
    # apart, is refined again from guesses moved along their step, 0.1 m apart up to this far (m; 0:
    # not): a front-end step matched 0.3 m short down a corridor (intel seed 1, 736-737) is beyond one
    # refinement's reach of the graph's guess, and the pairs beside it carry the same error.
    final_pair_search: float = 0.4
    final_pair_search_nodes: int = 10
    # A near pair (at most ``final_pair_search_nodes`` apart: the front end's steps again) is also refined
    # from the graph's guess turned this much either way (rad; 0: not), and the answer with most points
    # on a line taken (refused if outside the final window): where the two scans leave a plateau of poor
    # fits the refinement hardly turns from where it starts (aces seed 2, scans 333-334, a 31-degree turn
    # the front end had 9 degrees short: from the graph's guess the pair stayed 6.4 degrees short with 75
    # of 126 points on a line, from 3 degrees over it found 98). Every pair probed cost intel's replay a
    # third more CPU and bought nothing more on the bench; an answer with ``PAIR_PROBE_BELOW`` or more of
    # its points on a line is not on such a plateau and is not probed.
    final_pair_turn_probe: float = math.radians(3.0)
    # A node the final pass found ambiguous (``final_ambiguity_jump``) and no submap took is tied to no
    # scan more than ``final_pair_search_nodes`` nodes away either: a pair is refined from the graph's
    # guess, the very guess the ambiguity was about, and confirms it whatever it is. Left to its steps.
    # (intel's corrected log with ``long_loops``: node 456 lay 0.16 m off its neighbours before the
    # final pass; both submaps that saw it found it ambiguous, and two pairs 17 nodes back, refined from
    # there, held it 0.28 m off: its worst scan-measured revisit 0.298 m.)
    final_pair_skip_ambiguous: bool = True
    # The final pass's edges replace the online closures: these brought the graph near enough for the
    # final window, and the final pass matches every node again from there. Kept beside the final
    # edges, a marginal online closure outlives them where the final pass finds nothing to say
    # (intel's corrected log with ``long_loops``: node 455 matched 0.26 m and 2.7 degrees off at a score
    # of 0.53; the final pass took none of its submaps, and the closure held it and its neighbours
    # 0.2-0.3 m off).
    final_replaces_online: bool = True
    # The odometry's steps as edges of their own in the final graph, between consecutive nodes (0:
    # not), their translation held at this many times its sd as learned from the log itself: the
    # median offset between the odometry's steps and the front end's matched ones (so a slip or a bump
    # does not count; robust edges, so one such step does not bend the graph either). The front end's
    # chain drifts; odometry drifts on its own, not with it: where it is good (the corrected logs'
    # GMapping poses learn an sd of 1.4-1.6 cm a step; the front end's steps of 0.7-1 m are held at
    # 3-4 cm) it holds the map's length between submap matches; where it is poor it learns a wide sd
    # and weighs little. The heading is left to the front end and the matches: with it held too, the
    # corrected logs gained nothing more and the Freiburg hospital went 0.86 -> 1.22 m (0.90 m as kept).
    # Twice, chosen on the three-component runs (once came nearer the corrected logs' poses and
    # further from their scans). Kept: aces' corrected log 0.029 -> 0.023 m, intel's 0.032 -> 0.0297 m,
    # both 0.5 mm further from the relations their scans measure; docs/mapping-history.md, "The
    # odometry's steps in the final graph".
    final_odometry_margin: float = 2.0
    # Every final-pass edge (a submap match, small or large, and a scan pair) needs at least this share
    # of its inliers on surfaces seen from the side this scan sees them from (``min_facing_share``'s
    # test, which online checks ask only of large corrections). The final window is small, but a wall
    # 0.3 m thick is within its reach: intel's corrected log's scan 814 sees one from the corridor
    # below it, and three final-pass edges (0.44-0.51 of their inliers facing) laid that face on the
    # one the room above saw, 0.19 m across a step the raw log's odometry drives straight. A match onto
    # a thin partition's far side (true to a few centimetres) is dropped too; the final pass has matches
    # to spare (intel's corrected log: 21 of its 3 599 edges go; aces', Killian's: none). Kept: intel's
    # corrected log 0.0297 -> 0.0293 m, its scans' own sets 0.0125 -> 0.0119 m (docs/mapping.md, "Walls
    # seen from behind").
    final_min_facing_share: float = 0.6
    # Before the final pass, the online closures that were large corrections (over ``confirm_above``:
    # each believed on a second node's word) are weighed against everything else once more. Grouped
    # with the closures beside them (their nodes within ``conflict_gap_nodes`` of the one before, their
    # submaps' first nodes within ``conflict_anchor_nodes``), a group whose removal lowers the solved
    # graph's chi2 by more than ``conflict_chi2``, and by more than ``conflict_chi2_per_closure`` per
    # closure in it, is let go and the graph solved again, the worst per closure first, at most
    # ``conflict_drops`` groups (0: off). A look-alike taken where the front end had drifted far
    # holds its few nodes in the wrong place; the true closures that come later are many, and the
    # graph bends the front end's chain between the two: each step a little, none past ``max_chi2``.
    # MIT's Killian Court: node 847, mid-turn, matched a submap 7.1 m along a corridor that repeats
    # itself and was confirmed by node 849 (three closures, 69 of the graph's chi2 of 201 theirs
    # alone, 23 a closure); the fifteen true ones at 1 315-1 390 s 53 (3.5 a closure). Let go, the
    # final pass finds the true place: 0.114 -> 0.041 m. The other published logs' largest groups
    # weigh 2.4 (aces), 3.4 (intel), 0.6 (fr079) and 28 (mit-csail, 9 a closure): none goes. One group
    # at most: letting a group go bets that the final pass finds the true place, and each more is a
    # bet on a graph the last one changed (Killian with ``long_loops``: 0.147 m as it was, 0.130 m
    # with one group let go, 0.179 m with three, the last two partly right).
    conflict_chi2: float = 20.0
    conflict_chi2_per_closure: float = 15.0
    conflict_gap_nodes: int = 20
    conflict_anchor_nodes: int = 30
    conflict_drops: int = 1
    # The same weighing online, where no final pass runs (a robot). A group is complete once the newest
    # node is ``conflict_gap_nodes`` past its last closure and no large correction waiting for its
    # confirmation lies that near it (none can join it then). Whenever the complete groups holding a
    # large correction are not those weighed last, at a solve while mapping, each is taken out of a copy
    # of the graph, and each pair of heavy ones (each over ``conflict_chi2``) together too. Two groups in
    # conflict bend the same chain: taking out either relieves it, so both together lower the chi2 by
    # less than the two alone, summed. Of the groups in a pair short by more than ``conflict_pair_chi2``
    # (0: off), the one worst per closure goes, if over ``conflict_chi2_per_closure``: one a weighing.
    # A pair is needed: a true return after a long drift is as heavy when it arrives, with nothing to
    # conflict with (mit-csail's at 404 s: 84 for its three closures, 28 a closure). MIT's Killian
    # Court: the look-alike and the true closures 100 s later, 68 and 53 alone, 50 less together; its
    # other pairs of heavy groups within 0.4 of their sum. Only the newest ``conflict_online_groups``
    # complete groups are weighed: a weighing solves the whole graph once, once per group and once per
    # heavy pair, in the mapping thread (Killian's look-alike went when three groups were complete, and
    # the log never had more than twelve).
    conflict_pair_chi2: float = 20.0
    conflict_online_groups: int = 10
    cached_submaps: int = 16  # drawn submaps kept (least recently used dropped; drawn again if needed)
    check_period: float = 0.0  # s: a node's fresh search at least this long after the last one's (0: every node)
    # ``take`` (a search run elsewhere, on a robot) solves at most once per len(graph) / this seconds:
    # a solve costs about in proportion to the graph, so its share of a core stays flat however long
    # the robot maps (0: as soon as something is found, as ``close`` does).
    solve_nodes_per_s: float = 0.0
    # ``close`` (a replay): a closure moving its node less than ``lazy_solve_below`` m (a turn as its arc
    # at ``JUMP_LEVER_M``) joins the graph at once but is solved with the next one that moves more, or
    # once ``lazy_solve_share`` x len(graph) nodes have passed since the last solve. A solve costs about
    # in proportion to the graph and a robot back in a mapped room closes at nearly every node, so
    # solving each made long replays quadratic (intel driven 4x: 3 640 scans in 340 s, 910 in 23 s);
    # spaced in proportion, a solve's cost per node stays flat. Below 1 000 nodes nothing waits (the
    # real logs' figures are unchanged to the bit); at 17 000 a small correction waits 17 nodes.
    lazy_solve_below: float = 0.1
    lazy_solve_share: float = 0.001

    def __post_init__(self) -> None:
        if self.submap_nodes < 2 or self.attempts_per_node < 0 or self.min_gap_nodes < self.submap_nodes:
            raise ValueError("need submap_nodes >= 2, attempts_per_node >= 0 and min_gap_nodes >= submap_nodes")
        if self.bnb_depth < 1 or self.max_drops < 0 or self.cached_submaps < 1:
            raise ValueError("need bnb_depth >= 1, max_drops >= 0 and cached_submaps >= 1")
        for name in (
            "search_radius",
            "search_xy",
            "search_theta",
            "angle_step",
            "closure_sigma_xy",
            "closure_sigma_theta",
            "step_sigma_xy",
            "step_sigma_theta",
            "max_chi2",
            "final_radius",
            "final_window_xy",
            "final_window_theta",
            "final_sigma_xy",
            "final_sigma_theta",
            "final_pair_radius",
            "final_pair_turn",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        for name in (  # 0 turns these off
            "final_per_node",
            "final_any_heading",
            "final_min_gap_nodes",
            "final_drops",
            "final_partial_sigma",
            "final_ambiguity_jump",
            "final_pair_per_node",
            "final_pair_weak",
            "final_pair_search",
            "final_pair_turn_probe",
            "final_pair_search_nodes",
            "final_wide_window_xy",
            "final_wide_min_gap_nodes",
            "lazy_solve_below",
            "lazy_solve_share",
            "confirm_apart_m",
            "confirm_apart_rad",
            "confirm_apart_share",
            "odometry_gain",
            "odometry_floor",
            "odometry_theta_floor",
            "fill_max_gap",
            "fill_from_range",
            "fill_depth_share",
            "fill_depth_m",
            "final_odometry_margin",
            "conflict_chi2",
            "conflict_chi2_per_closure",
            "conflict_gap_nodes",
            "conflict_anchor_nodes",
            "conflict_drops",
            "conflict_pair_chi2",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        if not self.odometry_max_search_xy >= self.search_xy:  # also refuses NaN
            raise ValueError(f"odometry_max_search_xy must be >= search_xy, got {self.odometry_max_search_xy!r}")
        if self.final_pair_gap_nodes < 1 or not 0.0 <= self.final_pair_inliers <= 1.0:
            raise ValueError(
                "need final_pair_gap_nodes >= 1 (not a node against itself) and 0 <= final_pair_inliers <= 1"
            )
        if not self.conflict_online_groups >= 2:  # a pair at least
            raise ValueError(f"conflict_online_groups must be >= 2, got {self.conflict_online_groups!r}")
        if self.max_search_xy < self.search_xy or self.max_search_theta < self.search_theta:
            raise ValueError("the search caps must be at least the base windows")
        for name in ("min_facing_share", "final_min_facing_share"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        for name in ("large_min_score", "large_min_score_unfilled"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")


def long_loops(config: CloserConfig | None = None) -> CloserConfig:
    """``config`` (default: the defaults) for a log of loops hundreds of metres long: each candidate
    submap searched in its own window (``window_per_submap``) and three checks a node, so a far submap
    the drifted graph ranks behind nearer look-alikes is still tried where the robot is. MIT's Killian
    Court (1.9 km, published relations): 0.254 m by default (``far_loop_m``: submaps 250 m or more back
    along the graph get such windows; 1.649 m without; 0.115 m since ``large_min_score_unfilled``),
    0.146 m with this (with that floor too: the default now does better there); the Freiburg hospital
    0.862 -> 0.595 m. Elsewhere the means move a millimetre or less and single worst revisits
    either way (aces' published 0.180 -> 0.225 m, intel's corrected 0.293 -> 0.255 m), but for the
    corrected csail log, 0.031 / 0.20 -> 0.040 / 0.40 m: docs/mapping.md, "``--long-loops`` on every
    log". ``fleetlink map replay --long-loops``."""
    return replace(config or CloserConfig(), window_per_submap=True, attempts_per_node=3)


def open_space(config: CloserConfig | None = None) -> CloserConfig:
    """``config`` (default: the defaults) with every submap drawn filled, whatever the range its walls
    were seen at (``fill_from_range`` 0), a fresh large correction asked ``large_min_score`` there. By
    default only submaps that saw their walls 5 m off or more are filled. Measured on corrected logs
    replayed on their own poses (complete relations, mean / worst revisit, default -> this): the Acapulco
    convention hall 0.079 / 3.18 -> 0.070 / 2.62 m, MIT's infinite corridor 0.059 / 0.93 -> 0.051 /
    0.37 m, the Freiburg campus the same; the offices' published relations a little worse (aces' worst
    revisit 0.180 -> 0.199 m, intel's 0.093 -> 0.096 m). ``fleetlink map replay --open-space``."""
    return replace(config or CloserConfig(), fill_from_range=0.0)


def replay_closer(*, open_space_fill: bool = False, long_loops_search: bool = False) -> CloserConfig:
    """The closer ``fleetlink map replay`` maps with: the defaults, with ``open_space`` (``--open-space``)
    and ``long_loops`` (``--long-loops``) where asked; the bench replays with the same."""
    config = CloserConfig()
    if open_space_fill:
        config = open_space(config)
    if long_loops_search:
        config = long_loops(config)
    return config


@dataclass(frozen=True, slots=True)
class NodeScan:
    """A keyframe's scan in the sensor frame: the prepared beams (for drawing a submap), the kept
    points with their normals (point-to-line) and the thinned points (correlative search)."""

    ranges: F64
    angles: F64
    hit: npt.NDArray[np.bool_]
    points: F64
    normals: F64
    match_points: F64


@dataclass(frozen=True, slots=True)
class Closure:
    node: int  # the new node
    anchor: int  # the first node of the submap it was matched against
    z: Pose  # the new node's pose in the anchor's frame
    score: float  # the field score on the submap (a scan pair: its inlier share, ``Closure.pair``)
    inlier_ratio: float
    # A partial match (final pass, ``final_partial_sigma``): the unit direction, in the anchor's frame,
    # along which it fixes nothing (a corridor's axis); None: it fixes every direction.
    weak_dir: tuple[float, float] | None = None
    # A final-pass scan pair (``final_pair_per_node``): ``anchor`` is then the other node, not a submap's first.
    pair: bool = False


@dataclass(frozen=True, slots=True, eq=False)
class SubmapField:
    """A drawn submap's likelihood field alone (``matcher.FieldMap``): its log-odds grid is let go once
    the field is made (a check reads only the field), 15 % of what a drawn submap held."""

    field: npt.NDArray[np.float32]
    origin: tuple[float, float]
    resolution: float


@dataclass(frozen=True, slots=True, eq=False)
class Drawn:
    """A submap drawn for verification, in its first node's frame: its likelihood field, the
    point-to-line map, and the branch and bound's levels. Read only once drawn."""

    grid: SubmapField
    local: LocalMap
    grids: PrecomputedGrids
    filled: bool = False  # drawn with its surfaces filled (``CloserConfig.fill_max_gap``)


@dataclass(frozen=True, slots=True, eq=False)
class Check:
    """One verification of a node against a submap, self-contained: ``run_check`` needs nothing else,
    so it can run on another thread while the graph goes on growing (the verdict, a relative pose, is
    valid whatever the graph does meanwhile)."""

    node: int
    submap: int  # its index in ``LoopCloser.submaps``
    anchor: int  # the submap's first node (its frame)
    scan: NodeScan
    guess: Pose  # the node's sensor pose in the submap's frame
    window: tuple[float, float]  # (m, rad) half-widths of the search
    drawn: Drawn | None  # the submap as drawn, or None: draw it from ``parts``
    parts: tuple[tuple[Pose, NodeScan], ...]  # (sensor pose in the submap's frame, scan) per node
    config: CloserConfig
    grid_config: GridConfig
    mount: Pose  # the lidar on the robot
    confirms: Closure | None = None  # a pending closure this check may confirm (else a fresh search)
    owner: object = field(default=None, compare=False)  # the closer that planned it (``take`` ignores others')
    partial: bool = False  # a match ill-posed along one direction only is kept as a partial closure
    unique: bool = False  # a match away from the guess is refused when the guess is a match too
    far: bool = False  # a far loop's check (``far_loop_m``): its drawing is not kept in the cache
    final: bool = False  # a final-pass check: every match it accepts needs ``final_min_facing_share``


@dataclass(frozen=True, slots=True, eq=False)
class CheckResult:
    check: Check
    closure: Closure | None
    # "accepted", "few points", "score", "inliers", "behind", "disagreement", "outside", "degenerate",
    # "ambiguous", "far side" (a final-pass match otherwise accepted: ``final_min_facing_share``)
    outcome: str
    drawn: Drawn | None  # the submap as drawn for the check (None: not drawn, too few points)


@dataclass(slots=True, eq=False)
class _Submap:
    first: int
    last: int  # exclusive
    drawn: Drawn | None = None
    tried_at: int = -(10**9)
    far_tried_at: int = -(10**9)  # a far loop's check (``far_loop_m``): it does not hold back a near one


@dataclass(slots=True)
class CloserStats:
    attempts: int = 0
    accepted: int = 0
    rejected_score: int = 0
    rejected_inliers: int = 0
    rejected_behind: int = 0  # its walls matched from their far side (``min_facing_share``)
    rejected_disagreement: int = 0
    rejected_degenerate: int = 0
    rejected_outside: int = 0  # refined beyond the search window (slid down a corridor)
    rejected_ambiguous: int = 0  # a large correction where the graph's guess matched too (``large_unique``)
    far_loop_checks: int = 0  # fresh checks of submaps a long loop back along the graph (``far_loop_m``)
    final_pairs: int = 0  # the final pass's scan-to-scan edges (``final_pair_per_node``)
    final_pairs_searched: int = 0  # of them, found by the search (``final_pair_search``)
    dropped_by_solve: int = 0
    pending: int = 0  # large corrections held for a second closure
    confirmed: int = 0
    solves: int = 0
    submaps_drawn: int = 0  # drawings (a submap let go and needed again is drawn again)
    submaps_filled: int = 0  # ... of them, drawn with their surfaces filled (``fill_from_range``)
    final_edges: int = 0  # matches the final pass (``finish``) verified
    conflicts_dropped: int = 0  # online closures let go, the rest of the graph not bearing them out (``conflict_chi2``)
    conflicts_online: int = 0  # ... of them, online (``conflict_pair_chi2``)
    odometry_edges: int = 0  # the odometry's steps in the final graph (``final_odometry_margin``)
    odometry_sd_xy: float = 0.0  # m: ... and the sd they were held at
    steps_loosened: int = 0  # front-end steps the final solve held loosely (``final_loosen_steps``)
    final_ambiguous: int = 0  # ... and not kept: the graph's guess matched as well (``final_ambiguity_jump``)
    final_wide: int = 0  # of the final pass's matches, found only in the wider window (``final_wide_window_xy``)
    # final-pass matches and scan pairs that passed every other test, refused: walls seen from behind
    # (``final_min_facing_share``)
    final_behind: int = 0


class ClosureSearch(Protocol):
    """Where a mapper's closure checks run (``LoopCloser.plan`` -> here -> ``LoopCloser.take``)."""

    def submit(self, checks: list[Check]) -> None:
        """Run these checks (in order), their verdicts to be collected later."""
        ...

    def collect(self) -> list[CheckResult]:
        """The verdicts ready, in the order their checks were submitted; never waits."""
        ...

    @property
    def busy(self) -> bool:
        """Checks submitted whose verdicts are not ready yet (a new batch then waits its turn)."""
        ...


class DeferredSearch:
    """Checks run at once, in line, their verdicts collected with the next node: the results of a
    search elsewhere that always keeps up, deterministically (lockstep runs, tests)."""

    def __init__(self) -> None:
        self._done: list[CheckResult] = []

    def submit(self, checks: list[Check]) -> None:
        self._done.extend(run_check(c) for c in checks)

    def collect(self) -> list[CheckResult]:
        done, self._done = self._done, []
        return done

    @property
    def busy(self) -> bool:
        return False


class LoopCloser:
    """See the module docstring. ``add_node`` then ``close`` per keyframe; one owner."""

    def __init__(
        self,
        config: CloserConfig | None = None,
        grid: GridConfig | None = None,
        mount: Pose = (0.0, 0.0, 0.0),
    ) -> None:
        self.config = config or CloserConfig()
        self.grid_config = grid or GridConfig()
        self.mount = mount
        self.graph = PoseGraph()
        self.times: list[float] = []
        self.scans: list[NodeScan] = []
        self.submaps: list[_Submap] = []
        self.closures: list[Closure] = []
        self.stats = CloserStats()
        self._closure_edges: list[int] = []  # graph edge index per entry of ``closures``
        self._pending: list[Closure] = []  # large corrections waiting for a second closure
        self._far_pending: set[Closure] = set()  # ... those a far loop's check found (``_check``'s ``far``)
        self._large: set[Closure] = set()  # closures accepted as large corrections (``conflict_chi2``)
        self._weighed: frozenset[frozenset[Closure]] = frozenset()  # the groups weighed online last
        self._drawn: list[_Submap] = []  # the drawn submaps, least recently used first
        # The submap ``draw_occupancy`` drew last: its index, its scans at the poses drawn, its grid.
        self._shared: tuple[int, tuple[tuple[Pose, NodeScan], ...], LogOddsGrid] | None = None
        self._solved_at = -1  # the newest node at the last solve
        self._searched_t = -math.inf  # the time of the last node whose fresh search was planned
        self._far_searched_t = -math.inf  # ... whose far loops' checks were (``far_loop_m``)
        self._token = object()  # marks this closer's checks: a search host shared with a successor
        self._solved_t = -math.inf  # the newest node's time at the last solve
        self._unsolved = False  # closures added (or priors due) since the last solve
        self.since_closure = 0.0  # m travelled (node to node) since the last accepted closure or site prior
        self.odometry: list[Pose | None] = []  # the odometry's pose per node, where given (``add_node``)
        self._matched: list[bool] = []  # per node: the front end matched it (``add_node``'s ``information``)
        self._closed_at = 0  # the newest node when the last closure was accepted
        # m along the chain of front-end steps from node 0 to each node: an upper bound of the graph's
        # path (``_drift``), so a submap nearer than ``far_loop_m`` along it needs no graph search.
        self._chain_m: list[float] = []

    def __len__(self) -> int:
        return len(self.graph.poses)

    @property
    def poses(self) -> list[Pose]:
        return self.graph.poses

    def add_node(
        self,
        t: float,
        pose: Pose,
        scan: NodeScan,
        site: tuple[float, float, float] | None = None,
        information: F64 | None = None,
        odometry: Pose | None = None,
    ) -> int:
        """A keyframe at the front end's ``pose`` (the current frame); joined to the last node by the
        front end's relative pose. ``site``: (x, y, sd) where the site frame measured the node (a
        UWB-fused position), a prior that anchors the graph there. ``information``: the front end's
        match information on (x, y, theta) in the map frame (``icp_refine``), if it matched: where it is
        ill-posed along a direction (``step_degenerate_ratio``), the step is held loosely along it.
        ``odometry``: the odometry's own pose here (any frame; only its differences count), independent
        of the scans: the search window follows how far the front end has moved from it
        (``odometry_gain``)."""
        cfg = self.config
        if site is not None and not (all(math.isfinite(v) for v in site) and site[2] > 0):
            raise ValueError(f"site must be (x, y, sd) finite with sd > 0, got {site!r}")
        if odometry is not None and not all(math.isfinite(v) for v in odometry):
            raise ValueError(f"odometry must be finite, got {odometry!r}")
        k = self.graph.add_node(pose)
        if site is not None:
            self.graph.add_prior(k, site[:2], site[2])
            # A node the site frame measured is an anchor as good as a closure: the drift the window
            # allows for counts from here (a robot under UWB searches the base window only).
            self.since_closure = 0.0
            self._closed_at = k
        if k > 0:
            prev = self.graph.poses[k - 1]
            z = relative(prev, pose)
            d = math.hypot(z[0], z[1])
            sxy = cfg.step_sigma_xy + cfg.step_sigma_xy_per_m * d
            sth = cfg.step_sigma_theta + cfg.step_sigma_theta_per_rad * abs(z[2])
            info = np.diag([1.0 / sxy**2, 1.0 / sxy**2, 1.0 / sth**2])
            weak = None
            if cfg.step_degenerate_ratio > 0:
                weak = degenerate_direction(information, cfg.step_degenerate_ratio)
            if weak is not None:
                # The edge's error is in the node's own frame: the map-frame direction turned into it.
                c, s = math.cos(pose[2]), math.sin(pose[2])
                u = (c * weak[0] + s * weak[1], -s * weak[0] + c * weak[1])
                along = max(sxy, cfg.step_sigma_xy + cfg.step_degenerate_sigma_per_m * d)
                info = _weakened(info, u, along)
            self.graph.add_edge(k - 1, k, z, info)
            self.since_closure += d
            self._chain_m.append(self._chain_m[-1] + d)
        else:
            self._chain_m.append(0.0)
        self.times.append(t)
        self.scans.append(scan)
        self.odometry.append(odometry)
        self._matched.append(information is not None)
        if k % cfg.submap_nodes == 0:
            self.submaps.append(_Submap(k, k + 1))
        else:
            self.submaps[-1].last = k + 1
        return k

    def close(self) -> bool:
        """Look for closures of the newest node, in line; True when the graph was solved (poses moved)."""
        k = len(self.graph.poses) - 1
        if k < 0:
            return False
        cfg = self.config
        self._pending = [p for p in self._pending if k - p.node <= cfg.confirm_nodes]
        found: list[Closure] = []
        # A large correction is believed only when a second closure agrees with it: one match in a
        # building of look-alike corridors can be wrong with a good score. So while one waits, the
        # new node is first tried where that correction would put it, in a small window.
        for p in list(self._pending):
            for check in self._confirm_checks(k, p):
                c = self._note(run_check(self._with_drawn(check)))
                if c is not None and self._agree(p, c):
                    found.extend([p, c])
                    self._pending.remove(p)
                    self.stats.confirmed += 1
                    break
            if found:
                break
        if not found:
            for check in self._fresh_checks(k):
                self._classify(self._note(run_check(self._with_drawn(check))), found, check.far)
        return self._conclude(k, found)

    def plan(self, k: int | None = None) -> list[Check]:
        """The verifications for node ``k`` (default the newest), to run elsewhere (``run_check``) and
        bring back with ``take``: one per pending large correction (where it would put the node), and
        the fresh search, unless one was planned less than ``check_period`` ago (by node time)."""
        k = len(self.graph.poses) - 1 if k is None else k
        if k < 0:
            return []
        cfg = self.config
        self._pending = [p for p in self._pending if k - p.node <= cfg.confirm_nodes]
        checks = [c for p in self._pending for c in self._confirm_checks(k, p)]
        t = self.times[k]
        # A far loop's check is paced on its own, so that the near search goes on as without it.
        near, far = t - self._searched_t >= cfg.check_period, t - self._far_searched_t >= cfg.check_period
        if near or far:
            fresh = self._fresh_checks(k, near, far)
            if any(not c.far for c in fresh):
                self._searched_t = t
            if any(c.far for c in fresh):
                self._far_searched_t = t
            checks.extend(fresh)
        return checks

    def take(self, results: list[CheckResult]) -> bool:
        """Bring verdicts back (from ``plan``'s checks, run anywhere, in the order planned): drawn
        submaps cached, a confirmation agreeing with its pending closure accepts both, a fresh closure
        accepted or held as ``close`` does; then the graph solved if anything was found (or the priors
        are due a solve). True when the graph was solved (poses moved). Call it for every new node,
        with no results too."""
        k = len(self.graph.poses) - 1
        if k < 0:
            return False
        cfg = self.config
        found: list[Closure] = []
        for r in results:
            if r.check.owner is not self._token:
                continue  # planned by a closer before this one (a map restarted meanwhile)
            sm = self.submaps[r.check.submap]
            if r.drawn is not None and sm.drawn is None and not r.check.far:
                sm.drawn = r.drawn
                self._touch(sm)
            c = self._note(r)
            p = r.check.confirms
            if p is not None:
                if c is not None and p in self._pending and self._agree(p, c):
                    found.extend([p, c])
                    self._pending.remove(p)
                    self.stats.confirmed += 1
            else:
                self._classify(c, found, r.check.far)
        self._pending = [p for p in self._pending if k - p.node <= cfg.confirm_nodes]
        return self._conclude(k, found, paced=True)

    def _apart(self, p: Closure, b: int) -> bool:
        """Is node ``b`` far enough from the node of pending closure ``p`` to confirm it: turned
        ``confirm_apart_rad``, or ``confirm_apart_m`` and ``confirm_apart_share`` of the correction away?"""
        cfg = self.config
        pa, pb = self.graph.poses[p.node], self.graph.poses[b]
        d = math.hypot(pa[0] - pb[0], pa[1] - pb[1])
        return d >= max(cfg.confirm_apart_m, cfg.confirm_apart_share * self._jump(p)) or (
            abs(wrap(pa[2] - pb[2])) >= cfg.confirm_apart_rad
        )

    def _confirm_checks(self, k: int, p: Closure) -> list[Check]:
        cfg = self.config
        if not self._apart(p, k):
            return []  # a node this near sees what the pending closure's node saw: no second opinion
        fix = self._correction(p)
        at = compose(fix, self.graph.poses[k])
        self._far_pending &= set(self._pending)
        return [
            self._check(k, sm, fix, (cfg.search_xy, cfg.search_theta), confirms=p, far=p in self._far_pending)
            for sm, _ in self._candidates(k, at, fresh_only=False, limit=1)
        ]

    def _fresh_checks(self, k: int, near: bool = True, far: bool = True) -> list[Check]:
        """The fresh search's checks of node ``k``: the near candidates' (``near``) and the far loops'
        (``far``). A far loop's check leaves the near search as it was: its submap's mark, the cache
        of drawn submaps and the pace (``plan``) are its own."""
        checks = []
        far_loops = self.config.far_loop_m > 0 and not self.config.window_per_submap
        for sm, window in self._candidates(k, self.graph.poses[k]):
            is_far = far_loops and window is not None  # a far loop's own window (``_candidates``)
            if not (far if is_far else near):
                continue
            if is_far:
                sm.far_tried_at = k
                self.stats.far_loop_checks += 1
            else:
                sm.tried_at = k
            checks.append(self._check(k, sm, window=window, far=is_far))
        return checks

    def _note(self, r: CheckResult, attempt: bool = True) -> Closure | None:
        """Count a verdict in the stats (``attempt``: as a closure check); the closure, if accepted."""
        st = self.stats
        st.attempts += attempt
        if r.drawn is not None and r.check.drawn is None:
            st.submaps_drawn += 1
            st.submaps_filled += r.drawn.filled
        if r.outcome in ("score", "few points"):
            st.rejected_score += r.outcome == "score"
        elif r.outcome == "inliers":
            st.rejected_inliers += 1
        elif r.outcome == "far side":
            st.final_behind += 1
        elif r.outcome == "behind":
            st.rejected_behind += 1
        elif r.outcome == "disagreement":
            st.rejected_disagreement += 1
        elif r.outcome == "outside":
            st.rejected_outside += 1
        elif r.outcome == "degenerate":
            st.rejected_degenerate += 1
        elif r.outcome == "ambiguous" and r.check.unique:
            st.final_ambiguous += 1
        elif r.outcome == "ambiguous":
            st.rejected_ambiguous += 1
        return r.closure

    def _classify(self, c: Closure | None, found: list[Closure], far: bool = False) -> None:
        """A fresh closure: accepted when it moves its node little, else held for a second one that
        agrees (both accepted then). ``far``: a far loop's check found it (its confirmations are far
        loops' checks too: ``_confirm_checks``)."""
        if c is None:
            return
        if self._jump(c) <= self.config.confirm_above:
            found.append(c)
            return
        agree = [p for p in self._pending if self._apart(p, c.node) and self._agree(p, c)]
        if agree:
            found.extend([*agree, c])
            self._pending = [p for p in self._pending if p not in agree]
            self.stats.confirmed += 1
        else:
            self._pending.append(c)
            self.stats.pending += 1
            if far:
                self._far_pending.add(c)

    def _conclude(self, k: int, found: list[Closure], paced: bool = False) -> bool:
        """Closures found join the graph; the graph is solved when they did, or when the priors are due
        a solve (they alone pull the graph into the site frame, now and then). ``paced``: not sooner
        than ``len(graph) / solve_nodes_per_s`` seconds (node time) after the last solve; what waits
        is solved at a later node. True when the graph was solved."""
        cfg = self.config
        urgent = False
        if found:
            urgent = paced or max(self._jump(c) for c in found) >= cfg.lazy_solve_below
            self._add(found)
            self._unsolved = True
        elif self.graph.priors and k - self._solved_at >= cfg.prior_solve_nodes:
            self._unsolved = urgent = True
        if not self._unsolved:
            return False
        if not urgent and k - self._solved_at < cfg.lazy_solve_share * len(self.graph.poses):
            return False  # small corrections only, and a solve not long ago: later (``lazy_solve_below``)
        wait = len(self.graph.poses) / cfg.solve_nodes_per_s if paced and cfg.solve_nodes_per_s > 0 else 0.0
        if self.times[k] - self._solved_t < wait:
            return False
        self._solve_online(wait)
        return True

    def _closure_info(self) -> F64:
        cfg = self.config
        return np.diag([1.0 / cfg.closure_sigma_xy**2, 1.0 / cfg.closure_sigma_xy**2, 1.0 / cfg.closure_sigma_theta**2])

    def add_closures(self, closures: list[Closure]) -> None:
        """Put verified closures into the graph and solve it; a closure the solve finds inconsistent
        with the rest (error above ``max_chi2``) is dropped and the graph solved without it; then the
        groups of large corrections weighed against each other (``conflict_pair_chi2``)."""
        self._add(closures)
        self._solve_online()

    def _add(self, closures: list[Closure]) -> None:
        info = self._closure_info()
        for c in closures:
            if self._jump(c) > self.config.confirm_above:
                self._large.add(c)
            self.graph.add_edge(c.anchor, c.node, c.z, info)
            self.closures.append(c)
            self._closure_edges.append(len(self.graph.edges) - 1)
            self.stats.accepted += 1
        self.since_closure = 0.0
        self._closed_at = len(self.graph.poses) - 1

    def _correction(self, c: Closure) -> Pose:
        """The map-frame move the closure asks of its node: where it puts the node, from where it is."""
        return compose(compose(self.graph.poses[c.anchor], c.z), inverse(self.graph.poses[c.node]))

    def _jump(self, c: Closure) -> float:
        """How far the closure moves its node (m, a turn counted as its arc at ``JUMP_LEVER_M``)."""
        return _move(self.graph.poses[c.node], compose(self.graph.poses[c.anchor], c.z))

    def _agree(self, a: Closure, b: Closure) -> bool:
        """Do two closures ask for the same correction? Both applied to ``b``'s node, compared."""
        node = self.graph.poses[b.node]
        pa = compose(self._correction(a), node)
        pb = compose(self._correction(b), node)
        cfg = self.config
        return (
            math.hypot(pa[0] - pb[0], pa[1] - pb[1]) <= cfg.confirm_distance
            and abs(wrap(pa[2] - pb[2])) <= cfg.confirm_angle
        )

    def _candidates(
        self, k: int, at: Pose, *, fresh_only: bool = True, limit: int | None = None
    ) -> list[tuple[_Submap, tuple[float, float] | None]]:
        """Finished submaps far enough back with a node near ``at`` (the node's pose, or where a
        pending correction puts it), nearest first; ``fresh_only``: not tried in ``retry_nodes``, each
        with the window it is searched in (None: the one window, the base grown since the last closure).

        With ``window_per_submap`` a fresh search's window is each submap's own: ``_growth`` over the
        graph's shortest path between it and the node (``_drift``), and it is a candidate when the node
        lies within ``search_radius`` + that growth. A closure onto the loop just driven says nothing of
        how far the map has drifted from a corridor mapped an hour before: MIT's Killian Court came back
        after a 500 m loop 34 m and 8 degrees from the corridor it had mapped, and a closure 14 m earlier
        onto its own loop had shrunk the one window to 2.4 m."""
        cfg = self.config
        limit = cfg.attempts_per_node if limit is None else limit
        if limit == 0:
            return []
        here = np.array(at[:2])
        xyt = np.array(self.graph.poses)
        per_submap = fresh_only and cfg.window_per_submap
        radius = cfg.search_radius + (self._growth()[0] if fresh_only and not per_submap else 0.0)
        reach = cfg.search_radius + max(cfg.max_search_xy, cfg.odometry_max_search_xy)  # beyond any window
        drift: F64 | None = None
        near: list[tuple[float, int, _Submap, tuple[float, float] | None]] = []
        far: list[tuple[float, int, _Submap, tuple[float, float] | None]] = []  # ``far_loop_m``
        far_loops = fresh_only and not per_submap and cfg.far_loop_m > 0 and cfg.far_loop_checks > 0
        for i, sm in enumerate(self.submaps):
            if sm.last - sm.first < cfg.submap_nodes or sm.last > k - cfg.min_gap_nodes:
                continue
            nodes = xyt[sm.first : sm.last]
            gap = float(np.hypot(nodes[:, 0] - here[0], nodes[:, 1] - here[1]).min())
            window: tuple[float, float] | None = None
            # A window of the submap's own: every candidate's (``window_per_submap``), or a far loop's.
            far_loop = far_loops and radius < gap <= reach
            own = per_submap or far_loop
            # A far loop's check does not hold back the near one when the robot comes within the one
            # window of that submap a few nodes on (measured: aces' published log with far loops from
            # 130 m, not one of its 76 far checks accepted, but their marks delayed near ones there).
            if fresh_only and k - (sm.far_tried_at if far_loop else sm.tried_at) < cfg.retry_nodes:
                continue
            if own:
                if gap > reach:
                    continue  # cheaply, before the graph's paths are measured
                if far_loop and self._chain_m[k] - self._chain_m[sm.last - 1] < cfg.far_loop_m:
                    continue  # nearer than that along the chain, so along the graph too
                if drift is None:
                    drift = self._drift(k)
                part = drift[sm.first : sm.last]
                if far_loop and float(part.min()) < cfg.far_loop_m:
                    continue
                gxy, gth = self._growth(sm.first + int(np.argmin(part)), float(part.min()))
                if gap > cfg.search_radius + gxy:
                    continue
                window = (cfg.search_xy + gxy, cfg.search_theta + gth)
            elif gap > radius:
                continue
            # Rank by the node that saw most nearly what this one sees: near, and facing the same way
            # (a scanner looking the other way down a corridor sees other walls).
            d = np.hypot(nodes[:, 0] - here[0], nodes[:, 1] - here[1])
            turn = np.abs(np.remainder(nodes[:, 2] - at[2] + math.pi, 2.0 * math.pi) - math.pi)
            (far if far_loop else near).append((float(np.min(d + VIEW_LEVER_M * turn)), i, sm, window))
        near.sort(key=lambda e: (e[0], e[1]))
        far.sort(key=lambda e: (e[0], e[1]))
        far = far[: cfg.far_loop_checks]
        return [(sm, window) for _, _, sm, window in near[:limit] + far]

    def _drift(self, k: int) -> F64:
        """The path (m) from node ``k`` to every node through the graph: a front-end step counts its
        length, a closure nothing, and two nodes the site measured (UWB priors) are tied by it at no
        length. How far the map may have drifted between two nodes grows with it."""
        from scipy.sparse import coo_matrix  # here, not at import: as the solve's (posegraph)
        from scipy.sparse.csgraph import dijkstra

        n = len(self.graph.poses)
        ii, jj, z = self.graph.edge_arrays()
        # A step (an edge between neighbours) counts the length it measured; scipy's graphs take a
        # stored 0 for no edge, so a closure or a prior costs a nanometre.
        w = np.where(np.abs(ii - jj) == 1, np.hypot(z[:, 0], z[:, 1]), 0.0) + 1e-9
        priors = np.array(sorted({p.i for p in self.graph.priors}), dtype=np.int64)
        if len(priors):  # every measured node tied to one more node, the site
            ii = np.concatenate((ii, priors))
            jj = np.concatenate((jj, np.full(len(priors), n)))
            w = np.concatenate((w, np.full(len(priors), 1e-9)))
        m = coo_matrix((w, (ii, jj)), shape=(n + 1, n + 1)).tocsr()
        out: F64 = dijkstra(m, directed=False, indices=k)[:n]
        return out

    def _growth(self, j: int | None = None, d: float | None = None) -> tuple[float, float]:
        """How much wider than the base the search is (m, rad) between node ``j`` (default: the node of
        the last closure) and the newest, from the drift over the path ``d`` between them (default: the
        path since the last closure) and, where the nodes carry it, the front end's disagreement with
        the odometry between them."""
        cfg = self.config
        d = self.since_closure if d is None else d
        c, k = (self._closed_at if j is None else j), len(self.graph.poses) - 1
        if cfg.odometry_gain > 0 and k >= 0:
            oc, ok = self.odometry[c], self.odometry[k]
            if oc is not None and ok is not None:
                # The front end's path since the last closure seen from the odometry's.
                e = relative(relative(oc, ok), relative(self.graph.poses[c], self.graph.poses[k]))
                gxy = min(
                    cfg.drift_rate * d,
                    max(cfg.odometry_floor * d, cfg.odometry_gain * math.hypot(e[0], e[1])),
                    cfg.odometry_max_search_xy - cfg.search_xy,
                )
                gth = min(
                    cfg.drift_theta_per_m * d,
                    max(cfg.odometry_theta_floor * d, cfg.odometry_gain * abs(wrap(e[2]))),
                    cfg.max_search_theta - cfg.search_theta,
                )
                return gxy, gth
        return (
            min(cfg.drift_rate * d, cfg.max_search_xy - cfg.search_xy),
            min(cfg.drift_theta_per_m * d, cfg.max_search_theta - cfg.search_theta),
        )

    def _draw(self, sm: _Submap) -> Drawn:
        """The submap drawn (``Drawn``), the first time it is needed. Only ``cached_submaps`` stay drawn
        (the least recently used is let go and drawn again if asked for): each holds a grid and its
        search levels, megabytes apiece."""
        if sm.drawn is None:
            sm.drawn = draw_submap(self._parts(sm), self.grid_config, self.config)
            self.stats.submaps_drawn += 1
            self.stats.submaps_filled += sm.drawn.filled
        self._touch(sm)
        return sm.drawn

    def draw_occupancy(self, i: int) -> tuple[npt.NDArray[np.int8], float, tuple[float, float]]:
        """Submap ``i``'s map_server cells (-1 unknown, 0-100), drawn from its nodes' scans at the
        graph's poses now, in its first node's frame, cropped to the cells seen: what a robot shares
        of it (agent/mapping/keeper.py ``MapPublication.submaps``; the fleet map merges submaps).
        The open submap is shared again as it grows: while its earlier scans stand where they were
        drawn, only its new ones are drawn into the grid kept from last time (the same grid, to the
        bit, as drawing them all again)."""
        parts = self._parts(self.submaps[i])
        last = self._shared
        if (
            last is not None
            and last[0] == i
            and len(last[1]) <= len(parts)
            and all(a[1] is b[1] and a[0] == b[0] for a, b in zip(last[1], parts, strict=False))
        ):
            g = _submap_grid(parts[len(last[1]) :], self.grid_config, into=last[2])
        else:
            g = _submap_grid(parts, self.grid_config)
        self._shared = (i, parts, g)
        cells = g.occupancy()
        rows = np.flatnonzero((cells != -1).any(axis=1))
        cols = np.flatnonzero((cells != -1).any(axis=0))
        if not len(rows):
            return np.full((1, 1), -1, dtype=np.int8), g.resolution, g.origin
        r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        res = g.resolution
        return np.ascontiguousarray(cells[r0:r1, c0:c1]), res, (g.origin[0] + c0 * res, g.origin[1] + r0 * res)

    def _touch(self, sm: _Submap) -> None:
        """``sm`` used now: last in the cache's order; the least recently used beyond the cache let go."""
        if sm in self._drawn:
            self._drawn.remove(sm)
        self._drawn.append(sm)
        while len(self._drawn) > self.config.cached_submaps:
            self._drawn.pop(0).drawn = None

    def _parts(self, sm: _Submap) -> tuple[tuple[Pose, NodeScan], ...]:
        """The submap's scans with their sensor poses in its first node's frame (the graph's now)."""
        anchor = self.graph.poses[sm.first]
        return tuple(
            (compose(relative(anchor, self.graph.poses[n]), self.mount), self.scans[n])
            for n in range(sm.first, sm.last)
        )

    def _check(
        self,
        k: int,
        sm: _Submap,
        fix: Pose = (0.0, 0.0, 0.0),
        window: tuple[float, float] | None = None,
        confirms: Closure | None = None,
        far: bool = False,
    ) -> Check:
        """Node ``k`` against ``sm``, searched around the node's pose moved by ``fix`` (a pending
        correction) within ``window`` (default: the base window grown by the drift). ``far``: a far
        loop's check, which leaves the cache of drawn submaps as it was (its order too): the near
        search goes on as if it had not been made."""
        cfg = self.config
        if window is None:
            gxy, gth = self._growth()
            window = (cfg.search_xy + gxy, cfg.search_theta + gth)
        anchor = self.graph.poses[sm.first]
        guess = compose(relative(anchor, compose(fix, self.graph.poses[k])), self.mount)
        drawn = sm.drawn
        if drawn is not None and not far:
            self._touch(sm)
        parts = () if drawn is not None else self._parts(sm)
        i = self.submaps.index(sm)
        return Check(
            k,
            i,
            sm.first,
            self.scans[k],
            guess,
            window,
            drawn,
            parts,
            cfg,
            self.grid_config,
            self.mount,
            confirms,
            self._token,
            far=far,
        )

    def _verify_all(
        self,
        ks: Sequence[int],
        sm: _Submap,
        window: tuple[float, float],
        partial: bool = False,
        unique: bool = False,
        ambiguous: set[int] | None = None,
    ) -> list[Closure]:
        """Each node of ``ks`` matched against ``sm`` in line (the final pass: see ``_check``; all
        together, ``run_checks``), counted in the stats; the closures found, in the order of ``ks``.
        ``partial``: a match ill-posed along one direction only is kept as a partial closure; it and
        ``unique``: refused where the guess is a match too (``final_ambiguity_jump``); the nodes so
        refused are added to ``ambiguous``."""
        checks = []
        for k in ks:  # one by one: the first draws the submap, the rest find it drawn
            check = replace(self._check(k, sm, window=window), final=True)
            if partial or unique:
                check = replace(check, partial=partial, unique=self.config.final_ambiguity_jump > 0)
            checks.append(self._with_drawn(check))
        results = run_checks(checks)
        if ambiguous is not None:
            ambiguous.update(r.check.node for r in results if r.outcome == "ambiguous")
        return [c for r in results if (c := self._note(r, attempt=False)) is not None]

    def _with_drawn(self, check: Check) -> Check:
        """In line: the check with its submap drawn here, into the cache (unless the scan has too few
        points to be checked at all: then nothing is drawn, as ``run_check`` would not; a far loop's
        check leaves the cache as it was, ``_check``)."""
        sc = check.scan
        if check.drawn is not None or len(sc.match_points) < 10 or len(sc.points) < 10:
            return check
        if check.far:
            return check  # ``run_check`` draws it from the parts the check carries
        return replace(check, drawn=self._draw(self.submaps[check.submap]), parts=())

    def finish(self) -> int:
        """The final pass: every node matched against the finished submaps it sees (not its own nor
        one beside it, ``final_min_gap_nodes``; the ``final_per_node`` nearest by view within
        ``final_radius``), each in a small window around where the solved graph puts it; every verified
        match an edge (not one away from the guess where the guess matches too, ``final_ambiguity_jump``, nor one
        on walls seen from behind, ``final_min_facing_share``); then the graph solved again,
        the worst edges dropped one at a time as for closures (at most ``final_drops``). Dense
        constraints, after Cartographer's global SLAM: a node's pose becomes the average of many
        scan-to-submap matches instead of the front end's chain of steps, and places where no loop
        closure was verified online are tied to what was mapped there before. The online closures are
        let go once the pass has found anything (``final_replaces_online``), and before it the group of
        them the rest of the graph bears out least, if it is over the gates, is let go
        (``conflict_chi2``: a look-alike's bend would keep the pass's windows off the true place).
        The log's odometry joins the graph as edges on each step's translation
        (``final_odometry_margin``). Called once, at the end: returns the edges kept."""
        cfg = self.config
        n = len(self.graph.poses)
        if n == 0:
            return 0
        if self._unsolved:  # closures still waiting for a solve (``lazy_solve_below``)
            self._solve()
        if cfg.conflict_drops > 0:
            self._drop_conflicts()
        xyt = np.array(self.graph.poses)
        full = [i for i, sm in enumerate(self.submaps) if sm.last - sm.first >= cfg.submap_nodes]
        pairs: dict[int, list[int]] = {}  # submap -> nodes, so each submap is drawn once
        if full:
            starts = np.array([self.submaps[i].first for i in full])
            ends = np.array([self.submaps[i].last for i in full])
            cols = np.concatenate([np.arange(a, b) for a, b in zip(starts, ends, strict=True)])
            bounds = np.concatenate(([0], np.cumsum(ends - starts)[:-1]))
            for k0 in range(0, n, _FINAL_ROWS):  # in blocks of nodes: the (nodes x nodes) table stays small
                rows = xyt[k0 : k0 + _FINAL_ROWS]
                other = xyt[cols]
                d = np.hypot(rows[:, None, 0] - other[None, :, 0], rows[:, None, 1] - other[None, :, 1])
                turn = np.abs(np.remainder(other[None, :, 2] - rows[:, None, 2] + math.pi, 2.0 * math.pi) - math.pi)
                # Per submap, the node that saw most nearly what this one sees (as for candidates).
                rank = np.minimum.reduceat(d + VIEW_LEVER_M * turn, bounds, axis=1)
                ks = np.arange(k0, k0 + len(rows))
                gap = cfg.final_min_gap_nodes
                own = (ks[:, None] >= starts[None, :] - gap) & (ks[:, None] < ends[None, :] + gap)  # or a neighbour
                rank[own] = np.inf  # not its own
                dist = np.minimum.reduceat(d, bounds, axis=1)  # and by distance alone, whichever way it faced
                dist[own] = np.inf
                for r in range(len(rows)):
                    near = np.flatnonzero(rank[r] <= cfg.final_radius)
                    near = near[np.argsort(rank[r, near], kind="stable")][: cfg.final_per_node]
                    chosen = near.tolist()
                    if cfg.final_any_heading > 0:
                        more = np.flatnonzero(dist[r] <= cfg.final_radius)
                        more = more[np.argsort(dist[r, more], kind="stable")]
                        chosen += [j for j in more.tolist() if j not in chosen][: cfg.final_any_heading]
                    for j in chosen:
                        pairs.setdefault(full[j], []).append(k0 + r)
        found: list[Closure] = []
        window = (cfg.final_window_xy, cfg.final_window_theta)
        ambiguous: set[int] = set()
        for s_i in sorted(pairs):
            found += self._verify_all(
                pairs[s_i], self.submaps[s_i], window, partial=cfg.final_partial_sigma > 0, ambiguous=ambiguous
            )
        if cfg.final_wide_window_xy > cfg.final_window_xy:
            # A node no submap took in the small window, with submaps near it: searched again wider.
            anchored = {c.node for c in found}
            wide = (cfg.final_wide_window_xy, cfg.final_window_theta)
            gap = cfg.final_wide_min_gap_nodes
            for s_i in sorted(pairs):
                sm = self.submaps[s_i]
                loose = [k for k in pairs[s_i] if k not in anchored and not sm.first - gap < k < sm.last + gap]
                wider = self._verify_all(loose, sm, wide, unique=True, ambiguous=ambiguous)
                found += wider
                self.stats.final_wide += len(wider)
        if cfg.final_pair_per_node > 0:
            doubtful = ambiguous - {c.node for c in found} if cfg.final_pair_skip_ambiguous else set()
            found += self._scan_pairs(xyt, doubtful)
        if cfg.final_replaces_online and found:  # (none found: the online closures are all there is)
            self.graph.remove_edges(self._closure_edges)
            self.closures, self._closure_edges = [], []
        self._odometry_edges()
        info = np.diag([1.0 / cfg.final_sigma_xy**2, 1.0 / cfg.final_sigma_xy**2, 1.0 / cfg.final_sigma_theta**2])
        for c in found:
            edge_info = info
            if c.weak_dir is not None:
                # The edge's error is in the frame of the node's pose as measured (``c.z``).
                cz, sz = math.cos(c.z[2]), math.sin(c.z[2])
                u = (cz * c.weak_dir[0] + sz * c.weak_dir[1], -sz * c.weak_dir[0] + cz * c.weak_dir[1])
                edge_info = _weakened(info, u, cfg.final_partial_sigma)
            self.graph.add_edge(c.anchor, c.node, c.z, edge_info)
            self.closures.append(c)
            self._closure_edges.append(len(self.graph.edges) - 1)
        before = len(self.closures)
        self.stats.final_edges += len(found)
        self._solve(max_drops=cfg.final_drops, loosen=cfg.final_loosen_steps)
        return len(found) - (before - len(self.closures))

    def _drop_conflicts(self) -> None:
        """Let go the groups of online closures that the rest of the graph does not bear out
        (``conflict_chi2``): each group holding a large correction is taken out of a copy of the graph,
        solved as ``_solve`` solves, and the chi2 it lowers counted; the worst per closure over both
        gates goes, the graph is solved again, and the rest are weighed again."""
        cfg = self.config
        if not self._large:
            return
        for _ in range(cfg.conflict_drops):
            suspects = self._suspects()
            if not suspects:
                return
            base = self._chi2_without()
            worst: list[int] | None = None
            worst_share = 0.0
            for group in suspects:
                gain = base - self._chi2_without(group)
                share = gain / len(group)
                if gain > cfg.conflict_chi2 and share > max(cfg.conflict_chi2_per_closure, worst_share):
                    worst, worst_share = group, share
            if worst is None:
                return
            self._let_go(worst)

    def _solve_online(self, wait: float = 0.0) -> None:
        """A solve while mapping (``close``, ``take``, ``add_closures``): ``_solve``, then the groups of
        large corrections weighed against each other (``_weigh_conflicts``). ``wait``: the pace's time
        between solves (``solve_nodes_per_s``); the weighing's solves count against it, so the next
        solve waits for them too and the share of a core stays what the pace allows."""
        self._solve()
        self._solved_t += wait * self._weigh_conflicts()

    def _weigh_conflicts(self) -> int:
        """Online: the complete groups of large corrections weighed, and in pairs (``conflict_pair_chi2``),
        when they are not those weighed last; of the groups in a pair in conflict, the one worst per
        closure let go (over ``conflict_chi2_per_closure``) and the graph solved again. Returns the
        solves it made (each of a copy of the whole graph)."""
        cfg = self.config
        if cfg.conflict_pair_chi2 <= 0 or not self._large:
            return 0
        k = len(self.graph.poses) - 1
        gap = cfg.conflict_gap_nodes
        complete = []
        for g in self._suspects():
            first = min(self.closures[i].node for i in g)
            last = max(self.closures[i].node for i in g)
            # No closure can join it any more, a large correction waiting for its confirmation included.
            if last <= k - gap and not any(first - gap <= p.node <= last + gap for p in self._pending):
                complete.append(g)
        complete = complete[-cfg.conflict_online_groups :]
        key = frozenset(frozenset(self.closures[i] for i in g) for g in complete)
        if len(complete) < 2 or key == self._weighed:
            return 0
        self._weighed = key
        base = self._chi2_without()
        gains = [base - self._chi2_without(g) for g in complete]
        heavy = [i for i, gain in enumerate(gains) if gain > cfg.conflict_chi2]
        solves = 1 + len(complete)
        worst, worst_share = -1, cfg.conflict_chi2_per_closure
        for a, b in itertools.combinations(heavy, 2):
            solves += 1
            if gains[a] + gains[b] - (base - self._chi2_without(complete[a] + complete[b])) <= cfg.conflict_pair_chi2:
                continue  # apart, each bends its own part of the chain
            for i in (a, b):
                if gains[i] / len(complete[i]) > worst_share:
                    worst, worst_share = i, gains[i] / len(complete[i])
        if worst < 0:
            return solves
        self._let_go(complete[worst], online=True)
        return solves + 1

    def _let_go(self, group: Collection[int], online: bool = False) -> None:
        """A group of closures the rest of the graph does not bear out taken out, counted (``online``:
        while mapping), and the graph solved without it."""
        self._remove_closures(group)
        self.stats.conflicts_dropped += len(group)
        self.stats.conflicts_online += len(group) if online else 0
        self._solve()

    def _suspects(self) -> list[list[int]]:
        """The groups of closures (``_closure_groups``) holding a large correction."""
        return [g for g in self._closure_groups() if any(self.closures[k] in self._large for k in g)]

    def _chi2_without(self, drop: Sequence[int] = ()) -> float:
        """The chi2 of a copy of the graph without the closures ``drop``, solved as ``_solve`` solves."""
        g = copy.deepcopy(self.graph)
        g.remove_edges([self._closure_edges[k] for k in drop])
        g.optimize(fixed=None if g.priors else 0, iterations=self.config.iterations, tolerance=1e-5)
        return g.chi2()

    def _remove_closures(self, indices: Collection[int]) -> None:
        """Take the closures ``indices`` (into ``closures``) and their edges out of the graph; the
        other closures keep their edges (renumbered)."""
        edges = sorted(self._closure_edges[k] for k in indices)
        self.graph.remove_edges(edges)
        gone = set(indices)
        kept = [k for k in range(len(self.closures)) if k not in gone]
        self.closures = [self.closures[k] for k in kept]
        self._closure_edges = [self._closure_edges[k] - bisect.bisect_left(edges, self._closure_edges[k]) for k in kept]

    def _closure_groups(self) -> list[list[int]]:
        """The closures (indices into ``closures``) in groups: by node, each joins the group of the one
        before it when their nodes are within ``conflict_gap_nodes`` and their submaps' first nodes
        within ``conflict_anchor_nodes``."""
        cfg = self.config
        groups: list[list[int]] = []
        for k in sorted(range(len(self.closures)), key=lambda k: self.closures[k].node):
            c = self.closures[k]
            if groups:
                last = self.closures[groups[-1][-1]]
                if (
                    c.node - last.node <= cfg.conflict_gap_nodes
                    and abs(c.anchor - last.anchor) <= cfg.conflict_anchor_nodes
                ):
                    groups[-1].append(k)
                    continue
            groups.append([k])
        return groups

    def _odometry_edges(self) -> None:
        """The odometry's steps between consecutive nodes as robust edges on translation, its sd
        learned from its offsets to the front end's matched steps (``final_odometry_margin``)."""
        cfg = self.config
        if cfg.final_odometry_margin <= 0 or self.stats.odometry_edges:
            return
        closing = set(self._closure_edges)
        fronts = {
            e.i: e.z for n, e in enumerate(self.graph.edges) if e.j == e.i + 1 and not e.robust and n not in closing
        }
        steps: list[tuple[int, Pose]] = []
        offsets: list[float] = []
        for k in range(1, len(self.graph.poses)):
            a, b, front = self.odometry[k - 1], self.odometry[k], fronts.get(k - 1)
            if a is None or b is None or front is None:
                continue
            z = relative(a, b)
            steps.append((k, z))
            if self._matched[k]:  # an unmatched step is the odometry's own: no offset to learn from
                offsets.append(math.hypot(z[0] - front[0], z[1] - front[1]))
        if len(offsets) < ODOMETRY_MIN_STEPS:
            return
        sd = float(np.median(offsets)) / 1.1774  # the median length of a 2D Gaussian offset is 1.177 sd
        if sd < ODOMETRY_MIN_SD_XY:
            return  # the front end's steps are the odometry's (held to it): it has nothing more to say
        sd *= cfg.final_odometry_margin
        info = np.diag([1.0 / sd**2, 1.0 / sd**2, ODOMETRY_FREE_THETA])
        for k, z in steps:
            self.graph.add_edge(k - 1, k, z, info, robust=True)
        self.stats.odometry_edges = len(steps)
        self.stats.odometry_sd_xy = sd

    def _scan_pairs(self, xyt: F64, doubtful: Collection[int] = ()) -> list[Closure]:
        """The final pass's scan-to-scan matches (``final_pair_per_node``): node k against earlier
        nodes' scans near it, point-to-line from the graph's guess (searched along the step for a
        near pair the guess is too far off for, ``final_pair_search``); each kept one an edge j -> k (not one
        on scan j's walls seen from behind, ``final_min_facing_share``).
        A node of ``doubtful`` is paired only with nodes near it in the chain (``final_pair_skip_ambiguous``).
        The pairs do not depend on one another: all are refined together (``icp_refine_many``)."""
        cfg = self.config
        references: dict[int, LocalMap] = {}
        inv_mount = inverse(self.mount)
        pairs: list[tuple[int, int, Pose, bool]] = []  # (k, j, guess, near pair)
        for k in range(cfg.final_pair_gap_nodes, len(xyt)):
            sk = self.scans[k]
            if len(sk.points) < 10:
                continue
            other = xyt[: k - cfg.final_pair_gap_nodes + 1]
            d = np.hypot(other[:, 0] - xyt[k, 0], other[:, 1] - xyt[k, 1])
            turn = np.abs(np.remainder(other[:, 2] - xyt[k, 2] + math.pi, 2.0 * math.pi) - math.pi)
            near = np.flatnonzero((d <= cfg.final_pair_radius) & (turn <= cfg.final_pair_turn))
            near = near[np.argsort(d[near] + VIEW_LEVER_M * turn[near], kind="stable")][: cfg.final_pair_per_node]
            for j in near.tolist():
                sj = self.scans[j]
                if len(sj.points) < 10:
                    continue
                if (k in doubtful or j in doubtful) and k - j > cfg.final_pair_search_nodes:
                    continue
                if j not in references:
                    references[j] = LocalMap(1, 0.05)
                    references[j].add((0.0, 0.0, 0.0), sj.points, sj.normals)
                pj = (float(xyt[j, 0]), float(xyt[j, 1]), float(xyt[j, 2]))
                pk = (float(xyt[k, 0]), float(xyt[k, 1]), float(xyt[k, 2]))
                guess = relative(compose(pj, self.mount), compose(pk, self.mount))  # sensor k in sensor j
                pairs.append((k, j, guess, k - j <= cfg.final_pair_search_nodes))  # near: the front end's steps again
        found = self._pairs_match([(references[j], self.scans[k], g, steps) for k, j, g, steps in pairs])
        again: list[int] = []  # the pairs refined again by the search (``final_pair_search``)
        if cfg.final_pair_search > 0:
            again = [i for i, (m, p) in enumerate(zip(found, pairs, strict=True)) if m is None and p[3]]
            searched = self._pairs_search(
                [(references[pairs[i][1]], self.scans[pairs[i][0]], pairs[i][2]) for i in again]
            )
            for i, m in zip(again, searched, strict=True):
                found[i] = m
        by_search = set(again)
        out: list[Closure] = []
        for i, ((k, j, _, _), m) in enumerate(zip(pairs, found, strict=True)):
            if m is None:
                continue
            facing = _inliers(references[j], self.scans[k].points, m.pose, cfg.inlier_distance)[1]
            if facing < cfg.final_min_facing_share:
                self.stats.final_behind += 1  # scan j's walls matched from their far side
            else:
                self.stats.final_pairs_searched += i in by_search  # of the pairs kept, the searched ones
                z = compose(compose(self.mount, m.pose), inv_mount)  # node k in node j's frame
                # No submap is drawn for a pair, so no field score: its inlier share stands in.
                share = m.inliers / len(self.scans[k].points)
                out.append(Closure(k, j, z, share, share, pair=True))
        self.stats.final_pairs += len(out)
        return out

    def _pairs_match(self, pairs: Sequence[tuple[LocalMap, NodeScan, Pose, bool]]) -> list[IcpResult | None]:
        """Each (reference, scan, guess, probe) of ``pairs``: ``scan`` refined against ``reference`` from
        ``guess`` (and, ``probe``, from it turned ``final_pair_turn_probe`` either way: the answer with
        most points on a line): the answer if well posed, with ``final_pair_inliers`` of its points on a
        line, within the final window of the guess."""
        cfg = self.config
        found = self._pairs_refine([(ref, sc, g) for ref, sc, g, _ in pairs])
        # Only an answer with fewer than ``PAIR_PROBE_BELOW`` of its points on a line may lie on a
        # plateau of poor fits; past that a probe gains a point or two and lands on the same pose.
        plateau = [
            i
            for i, (m, (_, sc, _, probe)) in enumerate(zip(found, pairs, strict=True))
            if probe and (m is None or m.inliers < PAIR_PROBE_BELOW * len(sc.points))
        ]
        if plateau and cfg.final_pair_turn_probe > 0:
            turns = (-cfg.final_pair_turn_probe, cfg.final_pair_turn_probe)
            probes = self._pairs_refine(
                [
                    (pairs[i][0], pairs[i][1], (pairs[i][2][0], pairs[i][2][1], pairs[i][2][2] + t))
                    for i in plateau
                    for t in turns
                ]
            )
            for n, i in enumerate(plateau):
                for q in probes[n * len(turns) : (n + 1) * len(turns)]:
                    m = found[i]
                    if q is not None and (m is None or q.inliers > m.inliers):
                        found[i] = q
        for i, (m, (_, _, guess, _)) in enumerate(zip(found, pairs, strict=True)):
            if m is not None and (
                math.hypot(m.pose[0] - guess[0], m.pose[1] - guess[1]) > cfg.final_window_xy
                or abs(wrap(m.pose[2] - guess[2])) > cfg.final_window_theta
            ):
                found[i] = None
        return found

    def _pairs_refine(self, tasks: Sequence[tuple[LocalMap, NodeScan, Pose]]) -> list[IcpResult | None]:
        """Point-to-line of each (reference, scan, start) of ``tasks`` (no prior to speak of: the pair's
        own geometry decides); each answer if well posed with ``final_pair_inliers`` of its points on a
        line (within the refinement's 0.15 m reach), else None."""
        cfg = self.config
        answers = icp_refine_many(
            [(ref, sc.points, start) for ref, sc, start in tasks], (1.0, 1.0), 0.03, 0.15, 20, PAIR_TOLERANCE
        )
        return [
            m if m.inliers >= cfg.final_pair_inliers * len(sc.points) and m.weak >= cfg.final_pair_weak else None
            for m, (_, sc, _) in zip(answers, tasks, strict=True)
        ]

    def _pairs_search(self, pairs: Sequence[tuple[LocalMap, NodeScan, Pose]]) -> list[IcpResult | None]:
        """Each (reference, scan, guess) of ``pairs`` refined again from guesses moved along the step
        (``PAIR_SEARCH_STEP_M`` apart, up to ``final_pair_search``): the answer with most inliers, unless
        another well-posed answer apart from it has nearly as many (a look-alike down a corridor)."""
        cfg = self.config
        offsets = [
            sign * q * PAIR_SEARCH_STEP_M
            for q in range(1, int(cfg.final_pair_search / PAIR_SEARCH_STEP_M + 1e-9) + 1)
            for sign in (-1.0, 1.0)
        ]
        steps: list[tuple[float, float, float]] = []  # each guess's length and direction
        tasks: list[tuple[LocalMap, NodeScan, Pose]] = []
        for ref, sc, guess in pairs:
            d = math.hypot(guess[0], guess[1])
            ux, uy = (guess[0] / d, guess[1] / d) if d > 1e-6 else (1.0, 0.0)
            steps.append((d, ux, uy))
            tasks += [(ref, sc, (guess[0] + off * ux, guess[1] + off * uy, guess[2])) for off in offsets]
        tried = self._pairs_refine(tasks)
        out: list[IcpResult | None] = []
        for n, ((_, _, guess), (d, ux, uy)) in enumerate(zip(pairs, steps, strict=True)):
            answers: list[IcpResult] = []
            for m in tried[n * len(offsets) : (n + 1) * len(offsets)]:
                if m is None:
                    continue
                # Not a step shortened or lengthened by more than half: two scans taken a few tenths
                # apart down a corridor also fit where they were taken from one place (the published
                # aces log: adjacent nodes 0.38 m apart matched at 0.01 m, inlier share 0.92). Nor one
                # moved across the step: the search is for its length (``PAIR_ACROSS_M``).
                mx, my = m.pose[0] - guess[0], m.pose[1] - guess[1]
                if math.hypot(mx, my) <= 0.5 * d and abs(ux * my - uy * mx) <= PAIR_ACROSS_M:
                    answers.append(m)
            out.append(_unambiguous(answers))
        return out

    def _solve(self, max_drops: int | None = None, loosen: bool = False) -> None:
        """Solve; while the worst closure's error is above ``max_chi2``, drop it and solve again (at
        most ``max_drops`` times; the last solve is always after the last drop). One at a time: a
        wrong closure bends the graph and raises its neighbours' errors too, and they come back under
        the gate once it is gone. ``loosen``: a front-end step worse than the worst closure is held
        loosely instead, first (``final_loosen_steps``), each step once; a loosening counts as a drop."""
        cfg = self.config
        drops = cfg.max_drops if max_drops is None else max_drops
        self._solved_at = len(self.graph.poses) - 1
        self._solved_t = self.times[-1] if self.times else -math.inf
        self._unsolved = False
        fixed = None if self.graph.priors else 0  # priors anchor the graph; else its first node does
        loosened: set[int] = set()
        for attempt in range(drops + 1):
            self.graph.optimize(fixed=fixed, iterations=cfg.iterations, tolerance=1e-5)
            self.stats.solves += 1
            if not self._closure_edges or attempt == drops:
                return
            chi = self.graph.errors()
            worst = max(range(len(self._closure_edges)), key=lambda n: chi[self._closure_edges[n]])
            edge = self._closure_edges[worst]
            if loosen:
                closing = set(self._closure_edges)
                steps = [
                    i
                    for i, e in enumerate(self.graph.edges)
                    if i not in closing and i not in loosened and e.j == e.i + 1 and not e.robust
                ]  # (a robust edge between neighbours is the odometry's: ``_odometry_edges``)
                step = max(steps, key=lambda i: chi[i]) if steps else -1
                if step >= 0 and chi[step] > max(cfg.max_chi2, chi[edge]):
                    e = self.graph.edges[step]
                    d = math.hypot(e.z[0], e.z[1])
                    sxy = cfg.step_sigma_xy + cfg.step_degenerate_sigma_per_m * d
                    sth = 3.0 * (cfg.step_sigma_theta + cfg.step_sigma_theta_per_rad * abs(e.z[2]))
                    self.graph.replace_edge(step, np.diag([1.0 / sxy**2, 1.0 / sxy**2, 1.0 / sth**2]))
                    loosened.add(step)
                    self.stats.steps_loosened += 1
                    continue
            if chi[edge] <= cfg.max_chi2:
                return
            self.stats.dropped_by_solve += 1
            self._remove_closures([worst])
            loosened = {e - 1 if e > edge else e for e in loosened}


ODOMETRY_MIN_STEPS = 20
"""Fewer matched steps with odometry than this say too little of its worth: no odometry edges."""
ODOMETRY_MIN_SD_XY = 0.002
"""Odometry whose steps are within this (m, the learned sd) of the front end's matched ones is what the
front end's steps already say (the matcher held to it): not an independent measurement, no edges."""
ODOMETRY_FREE_THETA = 1e-6
"""The odometry edges' information on heading (1/rad^2): next to none, but positive definite."""
SUBMAP_GROW_M = 2.0
"""A submap grid grows in steps of this many metres (the mapper's grid uses 8 m)."""
JUMP_LEVER_M = 3.0
"""A closure's turn counts towards ``confirm_above`` as the arc it moves a wall this far away."""
_FINAL_ROWS = 256
"""Nodes ranked against every submap at once in the final pass."""
VIEW_LEVER_M = 2.0
"""Ranking candidates: a node facing another way counts as this many metres further per radian."""
PAIR_SEARCH_STEP_M = 0.1
"""A scan pair's search (``final_pair_search``) starts the refinement this far apart along the step:
within the point-to-line's 0.15 m reach of any answer in between."""
PAIR_ACROSS_M = 0.2
"""A scan pair's search keeps only answers within this of the graph's guess across the step. From
guesses moved along it, a pair the refinement holds poorly slid sideways onto a look-alike (the
corrected csail log, nodes 325-326: 0.26 m across, 243 inliers against the truth's 233; its worst
revisit 0.20 -> 0.36 m). At 0.1 m the published MIT CSAIL log lost pairs it needs (worst revisit
0.238 -> 0.391 m)."""
PAIR_TOLERANCE = 1e-3
"""A scan pair's point-to-line stops once a step moves it less than this (m, and rad). Cauchy-weighted,
it creeps the last millimetres a tenth of a millimetre a step: at the front end's 1e-4 a quarter of the
final pass's refinements ran all 20 iterations, and the pairs took most of the final pass's time. At
1e-3 the office tour's final pass costs 7.3 -> 4.9 CPU s; intel's and aces' published and corrected
figures move by 0.1 mm or less (aces' corrected worst revisit 0.138 -> 0.136 m), the other corrected
logs' means by a millimetre or less, but two worst revisits by more (the campus 0.355 -> 0.372 m,
freiburg-079 0.206 -> 0.210 m; docs/mapping-history.md, "The final pass's cost"); at 2e-3 aces'
corrected mean 0.0295 -> 0.0302 m."""
PAIR_PROBE_BELOW = 0.7
"""A near pair is probed from turned starts (``final_pair_turn_probe``) only when its answer from the
graph's guess has fewer than this share of its points on a line: the plateau the probes are for left
59 % (aces seed 2, scans 333-334). Past 0.8 a probe won a third of the time on the office tour and the
corrected aces log, by at most 2.5 % of the points, next to the same pose; skipping those cost the
office tour's final pass 4.9 -> 3.9 CPU s; with every pair probed, the campus and freiburg-079 figures
are the tolerance's above, to the millimetre. 0.7, not 0.8 (thirty-eighth session): the published
logs, the eleven corrected logs and the perturbed seeds the same or a hair better, the office tour's
final pass 2.8-3.0 -> 2.6-2.7 CPU s."""
PAIR_AMBIGUITY_M = 0.1
"""Two answers of a scan pair's search this far apart, the second with nine tenths of the first's
inliers or more, are a look-alike: the pair is not kept."""
FACING_SLACK = 0.1
"""An inlier's submap point may face away from the scan's sensor by this much (the cosine between its
normal and the ray back to the sensor, about 6 degrees past grazing: normals of walls seen edge-on are
noisy) and still count as seen from the same side."""


def _submap_grid(
    parts: tuple[tuple[Pose, NodeScan], ...],
    grid: GridConfig,
    fill: CloserConfig | None = None,
    into: LogOddsGrid | None = None,
) -> LogOddsGrid:
    """A submap's log-odds grid, its scans integrated at their sensor poses in its frame; its field
    left stale (refreshed once, over what the scans changed, by whoever reads it: the same field as
    refreshed per scan). With ``fill``, each scan's surfaces are filled between neighbouring hits
    (``CloserConfig.fill_max_gap``): for matching against; a shared map shows only what was seen.
    ``into``: a grid already drawn from the submap's earlier scans, which ``parts`` follow."""
    # A small growth step: the mapper's 8 m padding would make every submap a big grid.
    g = into if into is not None else LogOddsGrid(replace(grid, grow_step=SUBMAP_GROW_M))
    for sensor, sc in parts:
        r, a, hit = sc.ranges, sc.angles, sc.hit
        if fill is not None:
            fr, fa = surface_fill(
                r, a, hit, fill.fill_max_gap, fill.fill_depth_share, fill.fill_depth_m, grid.resolution
            )
            if fr.size:
                r, a = np.concatenate((r, fr)), np.concatenate((a, fa))
                hit = np.concatenate((hit, np.ones(fr.size, dtype=bool)))
        g.integrate(sensor, r, a, hit, refresh=False)
    return g


def draw_submap(parts: tuple[tuple[Pose, NodeScan], ...], grid: GridConfig, config: CloserConfig) -> Drawn:
    """A submap drawn from its scans at their sensor poses in its frame, for matching against."""
    depth = config.bnb_depth
    filled = config.fill_max_gap > 0 and _seen_from(parts) >= config.fill_from_range
    g = _submap_grid(parts, grid, config if filled else None)
    local = LocalMap(max(1, len(parts)), cell=0.05)
    g.refresh_stale()
    local.extend([(sensor, sc.points, sc.normals) for sensor, sc in parts])  # fused once, not per scan
    # The field kept, the rest of the grid (log-odds, seen cells, the coarse field) let go. (The field
    # as a view into the levels' padded copy would save as much again, but a view is not contiguous
    # and the field's lookups flatten it: a copy per lookup, +14 % CPU on the aces replay.)
    return Drawn(
        SubmapField(g.field, g.origin, g.resolution),
        local,
        PrecomputedGrids(g.field, g.origin, g.resolution, depth),
        filled,
    )


def _seen_from(parts: tuple[tuple[Pose, NodeScan], ...]) -> float:
    """How far off a submap's scans saw their walls: the median over its scans of each one's median hit
    range (0 when none hit anything)."""
    medians = [float(np.median(sc.ranges[sc.hit])) for _, sc in parts if sc.hit.any()]
    return float(np.median(medians)) if medians else 0.0


def run_check(check: Check) -> CheckResult:
    """One verification (pure; any thread): branch and bound of the node's scan over the submap's
    field in the check's window, Gauss-Newton on the field, point-to-line against the submap's
    points; accepted when the refined score, the inlier share, the two answers' agreement and the
    weakest information all pass (``CloserConfig``). The submap is drawn first if the check carries
    only its parts."""
    hit = _check_search(check)
    if isinstance(hit, CheckResult):
        return hit
    drawn = hit[0]
    found, score = _refine(drawn.grid, check.scan.match_points, hit[1])  # and the field score there
    if score < check.config.min_score:
        return CheckResult(check, None, "score", drawn)
    r = icp_refine(drawn.local, check.scan.points, found, found, (1.0, 1.0), 0.03, 0.15, iterations=12)
    return _check_judge(check, drawn, found, score, r)


def run_checks(checks: Sequence[Check]) -> list[CheckResult]:
    """``run_check`` of each of ``checks`` (a replay's final pass: every node checked against a submap),
    the Gauss-Newton on the field of those against one submap together (``_refine_many``) and the
    point-to-line refinements of all at once (``icp_refine_many``): the same answers to rounding."""
    out: list[CheckResult | None] = [None] * len(checks)
    hits: dict[int, list[tuple[int, Drawn, Pose]]] = {}  # per submap drawn, its checks' hits
    for i, c in enumerate(checks):
        hit = _check_search(c)
        if isinstance(hit, CheckResult):
            out[i] = hit
        else:
            hits.setdefault(id(hit[0]), []).append((i, *hit))
    passed: list[tuple[int, Drawn, Pose, float]] = []
    for group in hits.values():
        drawn = group[0][1]
        refined = _refine_many(drawn.grid, [(checks[i].scan.match_points, p) for i, _, p in group])
        for (i, _, _), (found, score) in zip(group, refined, strict=True):
            if score < checks[i].config.min_score:
                out[i] = CheckResult(checks[i], None, "score", drawn)
            else:
                passed.append((i, drawn, found, score))
    passed.sort(key=lambda p: p[0])
    answers = icp_refine_many(
        [(d.local, checks[i].scan.points, f) for i, d, f, _ in passed], (1.0, 1.0), 0.03, 0.15, iterations=12
    )
    for (i, drawn, found, score), r in zip(passed, answers, strict=True):
        out[i] = _check_judge(checks[i], drawn, found, score, r)
    return [r for r in out if r is not None]


def _check_search(check: Check) -> CheckResult | tuple[Drawn, Pose]:
    """``run_check``'s branch and bound: the verdict if it refuses the check, else the submap drawn and
    the best pose on its lattice."""
    cfg = check.config
    sc = check.scan
    if len(sc.match_points) < 10 or len(sc.points) < 10:
        return CheckResult(check, None, "few points", None)
    drawn = check.drawn or draw_submap(check.parts, check.grid_config, cfg)
    wxy, wth = check.window
    # The lattice answer scores lower than the refined one (far points are off by the angle step):
    # search with a lower floor, and gate on the refined score.
    hit = search(drawn.grids, sc.match_points, check.guess, wxy, wth, cfg.search_min_score, cfg.angle_step)
    if hit is None:
        return CheckResult(check, None, "score", drawn)
    return drawn, hit[0]


def _check_judge(check: Check, drawn: Drawn, found: Pose, score: float, r: IcpResult) -> CheckResult:
    """``run_check``'s last part: the verdict on ``r``, the point-to-line answer from ``found`` (the
    field's Gauss-Newton answer, scoring ``score``)."""
    cfg = check.config
    sc = check.scan
    grid, local = drawn.grid, drawn.local
    wxy, wth = check.window
    ratio, facing = _inliers(local, sc.points, r.pose, cfg.inlier_distance)
    if ratio < cfg.min_inlier_ratio:
        return CheckResult(check, None, "inliers", drawn)
    # How far it moves the node (the robot, as ``LoopCloser._jump`` measures it), not the sensor.
    robot = compose(r.pose, inverse(check.mount))
    large = _move(compose(check.guess, inverse(check.mount)), robot) > cfg.confirm_above
    if facing < cfg.min_facing_share and large:
        return CheckResult(check, None, "behind", drawn)
    floor = cfg.large_min_score if drawn.filled else cfg.large_min_score_unfilled
    if large and check.confirms is None and score < floor:
        return CheckResult(check, None, "score", drawn)
    if (
        math.hypot(r.pose[0] - found[0], r.pose[1] - found[1]) > cfg.max_disagreement
        or abs(wrap(r.pose[2] - found[2])) > cfg.max_disagreement_angle
    ):
        return CheckResult(check, None, "disagreement", drawn)
    weak_dir: tuple[float, float] | None = None
    if r.weak < cfg.min_weak:
        # A partial closure (``check.partial``): well posed across (its strong direction passes the
        # gate), not along: it is kept with no information along its weak direction to speak of.
        weak_dir = degenerate_direction(r.information, 0.0, cfg.min_weak, cfg.min_weak) if check.partial else None
        if weak_dir is None:
            return CheckResult(check, None, "degenerate", drawn)
    # The answer must lie where the search looked (its window, plus what the two refinements may
    # disagree by): refinements that slid beyond it went along a direction the walls hardly pin, a
    # corridor, to a look-alike the search never weighed against the guess. Measured on the published
    # aces log: a node matched 0.68 m from the graph's guess in a 0.3 m window, inlier share 0.93,
    # pulled two steps of 0.38 m down the corridor to 0.09 m each. A partial match may slide along
    # its weak direction (it says nothing there): only the rest of the move is held to the window.
    dx, dy = r.pose[0] - check.guess[0], r.pose[1] - check.guess[1]
    if weak_dir is not None:
        along = dx * weak_dir[0] + dy * weak_dir[1]
        dx, dy = dx - along * weak_dir[0], dy - along * weak_dir[1]
    if (
        max(abs(dx), abs(dy)) > wxy + cfg.max_disagreement
        or abs(wrap(r.pose[2] - check.guess[2])) > wth + cfg.max_disagreement_angle
    ):
        return CheckResult(check, None, "outside", drawn)
    # Two answers are a look-alike, not a correction. The final pass's matches away from the graph's
    # guess (``unique``): refined from the guess itself, does it pass too? A fresh search's large
    # correction (``large_unique``; a confirmation's guess carries the correction already): searched
    # again nearer the guess than the answer (half its distance), does anything there pass?
    moved = math.hypot(r.pose[0] - check.guess[0], r.pose[1] - check.guess[1])
    second: Pose | None = None
    if weak_dir is None and check.unique and moved > cfg.final_ambiguity_jump:
        second = check.guess
    elif weak_dir is None and cfg.large_unique and check.confirms is None and large:
        nearer = search(
            drawn.grids, sc.match_points, check.guess, min(wxy, 0.5 * moved), wth, cfg.search_min_score, cfg.angle_step
        )
        second = None if nearer is None else nearer[0]
    if second is not None:
        near, near_score = _refine(grid, sc.match_points, second)
        if near_score >= cfg.min_score:
            q = icp_refine(local, sc.points, near, near, (1.0, 1.0), 0.03, 0.15, iterations=12)
            if (
                math.hypot(q.pose[0] - r.pose[0], q.pose[1] - r.pose[1]) > cfg.final_ambiguity_jump
                and _inliers(local, sc.points, q.pose, cfg.inlier_distance)[0] >= cfg.min_inlier_ratio
            ):
                return CheckResult(check, None, "ambiguous", drawn)
    # Last, so that it refuses only what would be an edge (an ambiguous node stays one: ``_verify_all``).
    if check.final and facing < cfg.final_min_facing_share:
        return CheckResult(check, None, "far side", drawn)
    score = field_score(grid, sc.match_points, r.pose)
    closure = Closure(check.node, check.anchor, robot, score, ratio, weak_dir)
    return CheckResult(check, closure, "accepted", drawn)


def degenerate_direction(
    information: F64 | None, ratio: float, strong: float = 0.0, weak: float = math.inf
) -> tuple[float, float] | None:
    """The unit direction (x, y) along which a match's position is ill-posed, or None: the weaker
    eigenvector of the information's xy block when the stronger eigenvalue is at least ``strong``, the
    weaker below ``weak``, and (``ratio`` > 0) the stronger more than ``ratio`` times the weaker; None
    without information."""
    if information is None:
        return None
    ev, vec = np.linalg.eigh(information[:2, :2])
    if ev[1] < strong or ev[0] >= weak or (ratio > 0 and ev[1] <= ratio * max(float(ev[0]), 1e-12)):
        return None
    return float(vec[0, 0]), float(vec[1, 0])


def _unambiguous(answers: Sequence[IcpResult]) -> IcpResult | None:
    """The answer with most inliers, unless another well-posed answer ``PAIR_AMBIGUITY_M`` apart from it
    has nearly as many (0.9 of them: a look-alike down a corridor); None when there is none."""
    if not answers:
        return None
    best = max(answers, key=lambda a: a.inliers)
    for a in answers:
        apart = math.hypot(a.pose[0] - best.pose[0], a.pose[1] - best.pose[1])
        if apart > PAIR_AMBIGUITY_M and a.inliers >= 0.9 * best.inliers:
            return None
    return best


def _weakened(info: F64, u: tuple[float, float], sd: float) -> F64:
    """``info`` (isotropic in x and y) with sd ``sd`` along the unit direction ``u`` instead."""
    out = info.copy()
    out[:2, :2] += (1.0 / sd**2 - info[0, 0]) * np.outer(u, u)
    return out


def _move(was: Pose, at: Pose) -> float:
    """How far a node moves from ``was`` to ``at`` (m, a turn counted as its arc at ``JUMP_LEVER_M``)."""
    return math.hypot(at[0] - was[0], at[1] - was[1]) + JUMP_LEVER_M * abs(wrap(at[2] - was[2]))


def _inliers(local: LocalMap, points: F64, pose: Pose, distance: float) -> tuple[float, float]:
    """The share of ``points`` (sensor frame; ``pose`` the sensor's) within ``distance`` of a submap
    point, and of those the share whose submap point was seen from the side this scan sees it from:
    its normal (facing the sensors that saw it) faces this sensor too, to within ``FACING_SLACK``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    wx = pose[0] + c * points[:, 0] - s * points[:, 1]
    wy = pose[1] + s * points[:, 0] + c * points[:, 1]
    idx, dist = local.nearest_xy(wx, wy)
    near = dist <= distance
    count = int(np.count_nonzero(near))
    if not count:
        return 0.0, 0.0
    n = local.normals[idx[near]]
    rx, ry = pose[0] - wx[near], pose[1] - wy[near]
    facing = n[:, 0] * rx + n[:, 1] * ry > -FACING_SLACK * np.hypot(rx, ry)
    return count / max(1, len(points)), float(np.count_nonzero(facing)) / count
