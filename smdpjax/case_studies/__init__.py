"""The paper's three case studies (Table 1), as reconstructed in ``shared/benchmarks.md``.

Each constructor returns a ``CaseStudy``: the system, both partitions, the specification and
(for verification) the fixed controller, ready for ``abstract`` / ``synthesize`` / ``verify`` and
for Monte Carlo validation with ``simulate``.

* ``unicycle_2d(cells)``: linear 2-D unicycle, 8 headings, reach-avoid (rows 1-16).
* ``unicycle_3d(noise_cells)``: Coulomb-friction unicycle with a periodic heading (rows 17-28).
* ``temperature(rooms)``: n-room heating with multiplicative noise and a look-up-table
  controller, 15-step safety (rows 29-40).

Beyond the paper:

* ``unicycle_2d_dfa(cells, spec=)``: case study 1 told to visit A, then B, avoiding the
  obstacles (and, with ``spec="never_after"``, never the passage C after A): DFA specifications.
* ``robot_2d(cells)``: IMPaCT's 2-D robot (additive Gaussian noise, 441 actions), the benchmark of
  the direct IMDP bounds (``abstract(..., bounds="direct")``, ``benchmarks/direct_imdp.py``).
* ``double_integrator_4d(cells, noise_cells)``: a 4-D planar double integrator (additive Gaussian
  noise, 25 actions) for scaling past Table 1 (``benchmarks/scaling.py``; 32^4 cells by default).

These are reconstructions: the paper does not print its systems' equations. Compare with the
paper on sizes, timings, memory and the ordering of e_avg between classes, not on exact values.
"""

from .case_study import CaseStudy
from .double_integrator_4d import double_integrator_4d
from .robot_2d import robot_2d
from .temperature import temperature
from .unicycle_2d import unicycle_2d
from .unicycle_2d_dfa import unicycle_2d_dfa
from .unicycle_3d import unicycle_3d

__all__ = ["CaseStudy", "unicycle_2d", "unicycle_3d", "temperature", "robot_2d", "unicycle_2d_dfa", "double_integrator_4d"]
