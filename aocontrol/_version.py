"""The package version: its one source.

``pyproject.toml`` reads it (``[tool.setuptools.dynamic]``), results files, saved controllers,
reports and the calibration cache record it. On the ground floor so that every layer imports
it downward.
"""

__version__ = "0.1.0"
