"""Coarse registration: fused features (:mod:`.fusion`) and RANSAC on their matches (:mod:`.ransac`)."""
