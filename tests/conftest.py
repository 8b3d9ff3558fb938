"""Shared by every test folder: this folder is on ``sys.path`` (pytest's prepend import mode
puts a conftest's folder there), so tests import the daemons' doubles from
``daemon_doubles``."""
