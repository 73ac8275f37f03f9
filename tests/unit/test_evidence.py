"""No single vehicle revokes signs (hdmap/mapping/evidence.py with the existence
log-odds of hdmap/mapping/existence.py): a blind camera, a vehicle that reports "not seen"
everywhere or one that reports it for one sign on every pass moves nothing to revoked,
while a removed sign passed by a few honest vehicles is revoked within a handful of
passes. Fixed seeds; 40 standing signs, 300 passes."""

from __future__ import annotations

import numpy as np

from hdmap.mapping.evidence import EvidencePolicy, MissLedger, blind
from hdmap.mapping.existence import REVOKED, ExistenceConfig, status, update

POLICY = EvidencePolicy()
CFG = ExistenceConfig()


class Map:
    """Existence of ``n`` landmarks with the evidence rules: a miss moves the log-odds
    only when admitted, and revocation waits for enough vehicles."""

    def __init__(self, n: int) -> None:
        self.l = np.full(n, CFG.l_max)
        self.ledger = MissLedger(POLICY)

    def pass_(self, vehicle: str, t: float, ids: list[int], seen: list[bool]) -> None:
        no_misses = blind(seen, POLICY)
        for i, s, b in zip(ids, seen, no_misses, strict=True):
            if (not s and b) or not self.ledger.admit(i, vehicle, t, s):
                continue
            new = update(self.l[[i]], [s], [CFG.full_frames], CFG)[0]
            if new <= CFG.l_revoked and not self.ledger.revocable(i):
                new = CFG.l_revoked + 1e-6  # held just above until enough vehicles agree
            self.l[i] = new

    def revoked(self) -> list[int]:
        return [i for i, x in enumerate(self.l) if status(x, CFG) == REVOKED]


def test_a_blind_pass_reports_nothing_missing_but_its_detections_count():
    assert blind([False] * 5, POLICY).all()
    assert not blind([True, True, False], POLICY).any()
    assert not blind([True, False], POLICY).any()  # too few in view to judge the share
    assert blind([False, False], EvidencePolicy(min_seen=1)).all()  # saw none: with min_seen


def test_rogue_vehicles_revoke_nothing():
    rng = np.random.default_rng(5)
    m = Map(40)
    for k in range(300):
        t = 60.0 * k
        ids = sorted(rng.choice(40, 8, replace=False).tolist())
        honest = rng.random(8) < 0.9  # standing signs, detected 9 passes in 10
        m.pass_(f"veh-{k % 5}", t, ids, honest.tolist())
        m.pass_("rogue-all", t + 1, ids, [False] * 8)  # "not seen" everywhere
        half = [j % 2 == 0 for j in range(8)]  # sees half, "misses" the other half
        m.pass_("rogue-half", t + 2, ids, half)
        m.pass_("rogue-one", t + 3, [ids[0]], [False])  # always misses one sign
    assert m.revoked() == []


def test_a_removed_sign_passed_by_honest_vehicles_is_revoked_in_a_few_passes():
    m = Map(3)
    seen_others = [True, True]
    for k in range(20):
        m.pass_(f"veh-{k % 3}", 60.0 * k, [0, 1, 2], [False, *seen_others])  # 0 is gone
        if m.revoked():
            break
    assert m.revoked() == [0] and k + 1 <= 6  # five misses, at least two vehicles
    # passed all day by one vehicle only: held above revoked (one vehicle decides nothing)
    one = Map(3)
    for k in range(20):
        one.pass_("veh-0", 60.0 * k, [0, 1, 2], [False, True, True])
    assert one.revoked() == []


def test_misses_count_again_after_the_window_and_the_ledger_round_trips():
    led = MissLedger(POLICY)
    assert [led.admit(1, "a", t, False) for t in (0.0, 1.0, 2.0)] == [True, True, False]
    assert led.admit(1, "a", POLICY.window_s + 0.5, False)  # the first has aged out
    again = MissLedger.restore(POLICY, led.snapshot())
    assert again.snapshot() == led.snapshot()
    assert again.admit(1, "a", POLICY.window_s + 0.6, False) is False
    led.admit(1, "b", 3.0, True)  # a detection refutes the misses before it
    assert not led.revocable(1) and 1 not in led.snapshot()
    assert led.admit(1, "a", POLICY.window_s + 0.7, False)  # "a" has its say again
