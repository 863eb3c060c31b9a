"""Centralized BiRRT (OMPL's RRT-Connect) in the composite joint space of a task's arms.

The planner searches the 6k-D space of a k-arm task from the start to the goal
configuration. Validity comes from the project's own collision model (the geoms the
environment checks), evaluated by the compiled checker of :mod:`mjx_multiarm.geometry.checker`:
one call per state, one per edge (a ``MotionValidator`` that checks the straight motion at
0.05 rad resolution in every joint). The search stops at an iteration cap or a time cap;
only exact solutions count. Solutions are shortcut with OMPL's ``PathSimplifier``
(``reduceVertices`` then ``ropeShortcutPath``; edges through the same validator): after
decimation into environment steps its paths are as short as ``simplifyMax``'s B-spline
smoothing gives, at a quarter to a third of the planning time (benchmarks/RESULTS.md).

Determinism: OMPL's global seed is set from (seed, task id) before a fresh planner and
simplifier are built for each task, so a task's plan does not depend on what the process
planned before (resumed and distributed runs give identical results) unless the time cap
cuts the search.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from mjx_multiarm.geometry.checker import CollisionChecker
from mjx_multiarm.geometry.collision import SWEEP_RESOLUTION
from mjx_multiarm.geometry.robot import NUM_JOINTS

#: Outcomes of a planning attempt (stored as their index).
STATUSES = ("solved", "start_in_collision", "goal_in_collision", "out_of_bounds", "iteration_limit", "time_limit", "replay_collision")
SOLVED, START_IN_COLLISION, GOAL_IN_COLLISION, OUT_OF_BOUNDS, ITERATION_LIMIT, TIME_LIMIT, REPLAY_COLLISION = range(len(STATUSES))


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """Settings of the expert planner.

    Attributes:
      iterations: RRT-Connect iteration cap (paper 4000; original code 10000).
      time_limit: wall-clock cap per task (s).
      resolution: largest joint motion (rad) between two collision checks of an edge.
      range: longest tree extension (rad, Euclidean in the composite space).
      simplify: shortcut the solution path (vertex reduction, then rope shortcuts).
      attempts: plans tried per task (new seeds) until the decimated steps pass the
        environment's own swept check (see :mod:`mjx_multiarm.expert.solve`).
    """

    iterations: int = 4000
    time_limit: float = 60.0
    resolution: float = SWEEP_RESOLUTION
    range: float = 2.0
    simplify: bool = True
    attempts: int = 3

    def __post_init__(self):
        for name in ("iterations", "time_limit", "resolution", "range", "attempts"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")


@dataclasses.dataclass
class PlanResult:
    """One task's planning outcome.

    Attributes:
      status: index into :data:`STATUSES`.
      path: [n, k, 6] joint waypoints from start to goal (None unless solved).
      plan_s: wall-clock planning time (s), simplification included.
      iterations: RRT-Connect iterations used.
    """

    status: int
    path: np.ndarray | None
    plan_s: float
    iterations: int

    @property
    def reason(self) -> str:
        return STATUSES[self.status]


def task_seed(seed: int, task_id: int) -> int:
    """A nonzero 32-bit OMPL seed derived from (seed, task id)."""
    state = np.random.SeedSequence([seed & 0xFFFFFFFF, task_id & 0xFFFFFFFF, (task_id >> 32) & 0xFFFFFFFF]).generate_state(1)[0]
    return int(state) or 1


def plan(checker: CollisionChecker, start, goal, config: PlannerConfig = PlannerConfig(), seed: int = 1) -> PlanResult:
    """Plan from composite ``start`` to ``goal`` ([6k] each) with RRT-Connect."""
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    ou.setLogLevel(ou.LOG_NONE)
    clock = time.perf_counter()
    start, goal = np.asarray(start, np.float64), np.asarray(goal, np.float64)
    endpoints = checker.collided(np.stack([start, goal]))
    for status, config_ok in ((OUT_OF_BOUNDS, checker.in_bounds(start) and checker.in_bounds(goal)),
                              (START_IN_COLLISION, not endpoints[0]), (GOAL_IN_COLLISION, not endpoints[1])):
        if not config_ok:
            return PlanResult(status, None, time.perf_counter() - clock, 0)

    dim = len(start)
    space = ob.RealVectorStateSpace(dim)
    bounds = ob.RealVectorBounds(dim)
    for i in range(dim):
        bounds.setLow(i, float(checker.lower[i]))
        bounds.setHigh(i, float(checker.upper[i]))
    space.setBounds(bounds)
    si = ob.SpaceInformation(space)
    project = ob.RealVectorIdentityProjectionEvaluator(space)

    def read(state, out):
        project.project(state, out)
        return out

    buffers = np.empty((2, dim))

    def state_valid(state) -> bool:
        return checker.state_free(read(state, buffers[0]))

    class EdgeValidator(ob.MotionValidator):
        def checkMotion(self, s1, s2):  # noqa: N802 (OMPL's name)
            return checker.motion_free(read(s1, buffers[0]).copy(), read(s2, buffers[1]).copy())

    validator = EdgeValidator(si)
    si.setStateValidityChecker(state_valid)
    si.setMotionValidator(validator)
    si.setup()
    states = []
    for values in (start, goal):
        state = si.allocState()
        state[0:dim] = values.tolist()
        states.append(state)
    problem = ob.ProblemDefinition(si)
    problem.setStartAndGoalStates(states[0], states[1])

    ou.RNG.setSeed(seed)  # before the planner and simplifier allocate their generators
    planner = og.RRTConnect(si)
    planner.setRange(config.range)
    planner.setProblemDefinition(problem)
    planner.setup()
    iterations = [0]

    def capped() -> bool:
        iterations[0] += 1
        return iterations[0] > config.iterations

    remaining = max(1e-3, config.time_limit - (time.perf_counter() - clock))
    stop = ob.plannerOrTerminationCondition(ob.PlannerTerminationCondition(capped), ob.timedPlannerTerminationCondition(remaining))
    planner.solve(stop)
    used = min(iterations[0], config.iterations)
    if not problem.hasExactSolution():
        status = ITERATION_LIMIT if iterations[0] > config.iterations else TIME_LIMIT
        return PlanResult(status, None, time.perf_counter() - clock, used)
    path = problem.getSolutionPath()
    if config.simplify:  # measured: as short as simplifyMax after decimation, at a third of its checks
        simplifier = og.PathSimplifier(si)
        simplifier.reduceVertices(path)
        simplifier.ropeShortcutPath(path)
    waypoints = np.empty((path.getStateCount(), dim))
    for i in range(len(waypoints)):
        read(path.getState(i), waypoints[i])
    waypoints[0], waypoints[-1] = start, goal
    return PlanResult(SOLVED, waypoints.reshape(len(waypoints), -1, NUM_JOINTS), time.perf_counter() - clock, used)
