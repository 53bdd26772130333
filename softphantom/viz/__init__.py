"""Visualisation: PNG plots, 3-D views, the live view (``softphantom.viz.live``)."""
