"""Input and output: frame sources and recording, result writers, atomic files, analytic frames.

Every file the project writes goes through :mod:`pipeline.io.atomic`.
"""
