"""Baselines a user would otherwise pick, on the same samples as the U-Net: model-based phase-diversity
retrieval on the 8 PSFs (:mod:`.retrieval`), the U-Net + retrieval hybrid, a simulated Shack-Hartmann
sensor (:mod:`.shack_hartmann`), and the comparison (:mod:`.compare`, ``metadesign compare``)."""
