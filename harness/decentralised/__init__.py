"""The decentralised loop: every robot estimates the swarm's density and moves on its own.

The centralised loop forms one KDE of every position. But the KDE is a mean over robots,
``p_KDE = (1/N) sum_i phi_i`` with ``phi_i`` robot ``i``'s own kernel, so each robot can
*track* it from its own kernel and messages from its neighbours (Zheng and Lin, arXiv
2009.05366 / 2106.05318), run the project's fast density filter on what it tracks, and
move by the paper's law evaluated on its own estimate (a field law's cell values at its
own position, :func:`harness.robot_law.own_velocities`; the robots' step is
:meth:`harness.agents.Swarm.step_robots`). One idea per module:

* :mod:`~harness.decentralised.graph`: the communication graph, its Laplacian and
  algebraic connectivity;
* :mod:`~harness.decentralised.robot_kde`: each robot's KDE kernel on the grid;
* :mod:`~harness.decentralised.consensus`: dynamic average consensus (derivation,
  invariant, error bound, gain) and the messages it costs;
* :mod:`~harness.decentralised.filters`: the per-robot fast density filters, built from
  :mod:`~harness.decentralised.density` (the density step, compiled over robots) and
  :mod:`~harness.decentralised.row_solver` (one sparse LU over robots);
* :mod:`~harness.decentralised.metrics`: the estimates' spread and the network figures;
* :mod:`~harness.decentralised.estimator`: the assembly, and ``estimator=distributed``
  (:class:`DistributedEstimator`).
"""

from harness.decentralised.consensus import (
    DynamicAverageConsensus,
    consensus_weights,
    message_counts,
)
from harness.decentralised.estimator import (
    DistributedEstimate,
    DistributedEstimator,
    RobotEstimators,
)
from harness.decentralised.filters import RobotFilters
from harness.decentralised.graph import algebraic_connectivity, communication_graph
from harness.decentralised.metrics import central_gap_l2, consensus_l2

__all__ = [
    "DistributedEstimate",
    "DistributedEstimator",
    "DynamicAverageConsensus",
    "RobotEstimators",
    "RobotFilters",
    "algebraic_connectivity",
    "central_gap_l2",
    "communication_graph",
    "consensus_l2",
    "consensus_weights",
    "message_counts",
]
