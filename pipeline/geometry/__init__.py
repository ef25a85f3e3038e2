"""Geometry: from matched marker pixels to the skin surface in millimetres.

calibration (stereo chessboard) -> triangulation (apparent points) -> refraction (through the flat
acrylic + gel stack) -> surface (skin surface, height maps) -> merge (many taps into one map);
index_fit measures the stack's refractive indices from a press (``calibrate-refraction``).
"""
