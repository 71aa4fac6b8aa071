"""Figures an engineer reads: Bode plots with the measured response, ``compare`` overlays.

matplotlib is imported only when a figure is drawn, so the commands that
draw none do not pay for it.
"""
