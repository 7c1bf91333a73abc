"""The graded policy family of the closed-loop evaluation, by short name (standard library only: the CLIs' choices).

Vid2World ranks policies of graded quality; ours are graded by design, so the order of the degradations is known
before any run (``resim.eval.policy_ranking.graded_policies`` builds them): the trained pixel policy, the same
policy with seeded steering noise or a constant steering bias (per metre of curvature), and constant velocity
(reads only the speedometer). An under-trained checkpoint joins with ``resim eval closed-loop --also RUN``.
"""

VARIANTS = {"policy": "policy", "noise": "policy + steering noise 0.08/m", "bias": "policy + steering bias 0.05/m",
            "bias2": "policy + steering bias 0.1/m", "cv": "constant velocity"}
HELP = "; ".join(f"{k}: {v}" for k, v in VARIANTS.items())   # the CLIs' help
