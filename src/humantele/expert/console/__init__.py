"""The sonographer's console: a page served by the expert daemon on loopback.

:mod:`.server` serves it (:class:`ConsoleServer`; :mod:`.config`: :class:`ConsoleConfig`);
:mod:`.frames` is where its video comes from (:class:`FrameProvider`), :mod:`.video` the
frames to the pages through :mod:`.transport_webcodecs` (the default) or
:mod:`.transport_jpeg`, :mod:`.tracks` each track's times and figures; :mod:`.session` what
it needs of the session (:class:`ConsoleSession`); :mod:`.expert_view` what it reads of the
expert daemon (a protocol: the console never imports the daemon) and :mod:`.hook` the
console in the daemon; :mod:`.messages` the page's messages, :mod:`.protocol` the replies to
clicks, :mod:`.pageclient` one open page, :mod:`.heartbeat` its pings; :mod:`.tools` freeze,
cine, calipers and annotations on :mod:`.cine`'s frames; :mod:`.captures` captures, clips
and the session's list; ``web/`` the page.
"""

from humantele.expert.console.config import ConsoleConfig
from humantele.expert.console.frames import FrameProvider, SourceFrames
from humantele.expert.console.server import ConsoleServer
from humantele.expert.console.session import ConsoleSession

__all__ = ["ConsoleConfig", "ConsoleServer", "ConsoleSession", "FrameProvider", "SourceFrames"]
