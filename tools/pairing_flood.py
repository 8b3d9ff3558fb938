"""Wrong pairing codes against the headset page's credential, and the real headset's tries.

The attack of issue 34 §4, on the follower's own :class:`humantele.web.credential.Credential`
(the feed's settings: 5 at once then one per 5 s from an address, 50 then 2 a second in all)
driven by a simulated clock, so it gives the same figures on any machine: ``--addresses``
loopback addresses send ``--rate`` wrong codes a second in all for ``--seconds``, while the
headset (its own address) offers the right code every ``--every`` seconds. ``--paired``: the
headset had paired before the flood (a reconnect after a Wi-Fi drop); without it, its first
pairing falls in the flood.

    python tools/pairing_flood.py                  # the issue's flood, paired and new headset
"""

from __future__ import annotations

import argparse
import json

from humantele.web.credential import Credential, Verdict, new_code, normalize_code


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def flood(
    seconds: float = 26.0, rate: float = 149.0, addresses: int = 200, every: float = 2.0,
    paired: bool = True,
) -> dict:  # fmt: skip
    """The headset's tries during the flood and what they got; the wrong codes checked."""
    clock = Clock()
    code = new_code()
    cred = Credential(code, normalize=normalize_code, clock=clock)  # the feed's settings
    headset = "192.168.1.50"
    if paired:
        assert cred.check(code, headset) is Verdict.OK
    wrong = f"{(int(code) + 1) % 10**8:08d}"
    verdicts: dict[str, int] = {}
    refused = tries = 0
    n = int(seconds * rate)
    next_try = 1.0
    for i in range(n):
        clock.t = i / rate
        v = cred.check(wrong, f"127.0.0.{2 + i % addresses}")
        verdicts[v.value] = verdicts.get(v.value, 0) + 1
        if clock.t >= next_try:
            tries += 1
            refused += cred.check(code, headset) is not Verdict.OK
            next_try += every
    return {"paired_before": paired, "wrong_codes_sent": n, "wrong_codes": verdicts,
            "headset_tries": tries, "headset_refused": refused}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=26.0)
    p.add_argument("--rate", type=float, default=149.0, help="wrong codes a second, in all")
    p.add_argument("--addresses", type=int, default=200)
    p.add_argument("--every", type=float, default=2.0, help="the headset's tries, s apart")
    a = p.parse_args()
    for paired in (True, False):
        print(json.dumps(flood(a.seconds, a.rate, a.addresses, a.every, paired)))


if __name__ == "__main__":
    main()
