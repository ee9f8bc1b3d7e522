"""Layer 3: what the method is measured with — the BOP scorer (:mod:`.metrics`, equal to the BOP
toolkit) and the synthetic BOP datasets (:mod:`.synth`).
"""
