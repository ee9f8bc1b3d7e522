"""Layer 5: pictures and pages made from the artifacts — the HTML report (:mod:`.html`), its
charts (:mod:`.plots`), the feature, hypotheses and SAR figures, and an estimate drawn over
its image (:mod:`.overlay`). Nothing here is computed again but renders of poses."""
