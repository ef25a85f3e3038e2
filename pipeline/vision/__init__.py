"""Vision: from one camera image to certain marker ids.

detection (blobs) -> delaunay / nearest (compiled geometry) -> dtrc (ring coding, stereo pairing,
tracking) -> identity (the certainty rule that decides every id); tactip_id for monocular domes;
annotate draws the results.
"""
