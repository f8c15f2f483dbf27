"""Renders of the reconstructed scene and the incident report (HTML and PDF).

Stages: ``render`` (:mod:`workbench.report.render_stage`) and ``report`` (:mod:`workbench.report.report_stage`).
"""
