"""smdpjax: uncertain-MDP abstractions of stochastic control systems with guaranteed bounds.

The pipeline, one subpackage per step of the paper ("Beyond Interval MDPs", Gracia & Lahijanian):

* ``System`` and the noise distributions (``Gaussian``, ``Uniform``): Section 2.
* ``partition``: the phi-conservative state grid S and the noise partition C (Sections 2, 7).
* ``reach``: sound box enclosures of Reach(s, a, c) (interval and Jacobian bounds).
* ``abstraction``: IMDP (Lemma 1), 2I-MDP, MI-MDP (Definition 5) and SMDP (Definition 6), all
  built from the same reachable sets.
* ``synthesis``: robust dynamic programming (Proposition 1, Theorem 4), strategy and bounds.
* ``simulation``: the refined controller and Monte Carlo validation (Theorem 5).
* ``metrics``: e_avg, p_avg, memory, wall time (Section 7).
* ``gradients``: derivatives of p_low in the noise law and partition (implicit differentiation).
* ``sweep``: one vmapped synthesis over a batch of parameter values sharing a cluster structure.
* ``specification``: DFA and LTLf specifications over labelled regions, synthesized on the
  product with the DFA (``synthesize_product``), never built explicitly.

Importing smdpjax turns on JAX's float64 mode: reachable sets and probabilities are float64.
"""

import jax

jax.config.update("jax_enable_x64", True)

from . import abstraction, gradients, metrics, partition, reach, specification, sweep, synthesis  # noqa: E402
from .abstraction import IMDP, KINDS, MIMDP, SMDP, CompactIMDP, TwoLayerIMDP, abstract  # noqa: E402
from .noise import Distribution, Gaussian, Uniform  # noqa: E402
from .partition import AVOID, NONTERMINAL, REACH, NoiseGrid, StateGrid  # noqa: E402
from .simulation import Controller, SimulationResult, simulate, uniform_in_cells  # noqa: E402
from .specification import DFA, ProductController, Region, Specification, simulate_product  # noqa: E402
from .synthesis import ProductSolution, Solution, synthesize, synthesize_product, verify, verify_product  # noqa: E402
from .system import System  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "System", "Distribution", "Gaussian", "Uniform", "StateGrid", "NoiseGrid", "NONTERMINAL", "REACH", "AVOID",
    "abstract", "KINDS", "IMDP", "CompactIMDP", "TwoLayerIMDP", "MIMDP", "SMDP", "synthesize", "verify", "Solution", "Controller", "simulate",
    "SimulationResult", "uniform_in_cells", "abstraction", "gradients", "metrics", "partition", "reach", "sweep",
    "synthesis", "specification", "DFA", "Region", "Specification", "synthesize_product", "verify_product",
    "ProductSolution", "ProductController", "simulate_product",
]
