"""Layer 2: the method — :mod:`.geometry`, :mod:`.encoders`, :mod:`.render`, :mod:`.registration`
(fusion, RANSAC), :mod:`.refinement` (verification, selection, turns, ICP, SAR), the model side
(:mod:`.model_side`), the scene side (:mod:`.scene_side`) and the prior's candidates
(:mod:`.segmentation`). Pure functions over arrays, records and files: never the plan, the
stages or the commands.
"""
