"""The sonographer's console: a page served by the expert daemon on loopback.

:mod:`.server` serves it (:class:`ConsoleServer`, :class:`ConsoleConfig`); :mod:`.frames` is
where its video comes from (:class:`FrameProvider`); :mod:`.session` what it needs of the
session (:class:`ConsoleSession`); :mod:`.expert_view` what it reads of the expert daemon (a
protocol: the console never imports the daemon) and :mod:`.hook` the console in the daemon;
:mod:`.messages` the page's protocol; :mod:`.cine` the cine buffer; :mod:`.captures` captured
frames on disk; ``web/`` the page.
"""

from humantele.expert.console.frames import FrameProvider, SourceFrames
from humantele.expert.console.server import ConsoleConfig, ConsoleServer
from humantele.expert.console.session import ConsoleSession

__all__ = ["ConsoleConfig", "ConsoleServer", "ConsoleSession", "FrameProvider", "SourceFrames"]
