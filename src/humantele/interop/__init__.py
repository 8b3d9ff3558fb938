"""Interoperability with research tools: OpenIGTLink for 3D Slicer and PLUS (:mod:`.igtl`)."""
