"""Differential magnetic force sensing: Hall-effect sensor pairs across a compliant shell.

Modules: ``model`` (magnets, Hall sensors, silicone suspension), ``readings`` (one sample),
``base`` (the :class:`ForceSensor` interface), ``sim`` and ``hid`` (backends), ``calibration``
(least-squares readings -> force), ``contact`` (contact detector with hysteresis),
``sensors`` (config union and factory).
"""
