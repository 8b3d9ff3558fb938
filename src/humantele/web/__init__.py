"""Pieces both daemons' web pages use: the self-signed TLS certificate (:mod:`.tls`) and the
checks on what a page sends (:mod:`.guard`)."""
