"""Study layer: demo, command line and plots (imports control and sim, never imported by them).

Only :mod:`aocontrol.study.plot` imports matplotlib.
"""

__all__: list[str] = []
