"""Grasp-candidate samplers that are not SuperGrasp's Stage 1 (baselines' candidates, label sources)."""
