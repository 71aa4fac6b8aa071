"""What an engineer reads: tables and figures of identification and tracking (``figures``: the
identification table, poles against speed, tracks over time, the terminal progress bar), Bode plots with the
measured response and ``compare`` overlays (``identification``), residual tests (``residuals``).

matplotlib is imported only when a figure is drawn, so the commands that
draw none do not pay for it.
"""
