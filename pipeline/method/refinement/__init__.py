"""The refine stage's algorithms, after RANSAC: ICP (:mod:`.icp`), the turns of a hypothesis
(:mod:`.turns`), the verification of a pose against the depth and mask (:mod:`.verification`),
the choice among hypotheses (:mod:`.selection`) and the symmetry-aware refinement (:mod:`.sar`)."""
