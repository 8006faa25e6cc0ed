"""Thermal-error maths: loading measured runs, estimators, sensor selection,
regime ranking and the JSON model store. Runs on plain arrays; no protocols here.
"""
