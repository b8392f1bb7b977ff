"""The per-tenant rate limiter (api.rate_limit.RateLimiter) against the token bucket it documents: `rate` tokens a
second up to `burst`, one per request.

Independent truth: from an empty bucket, after t idle seconds exactly min(burst, floor(rate t)) requests pass at
once, whatever t (a minute or a day idle still gives at most `burst`); a fresh tenant starts full; tenants do not
share a bucket; a refused request is told how long until one token is back, and after that wait one passes. The
clock is a fake (the limiter reads time.monotonic), so the test is exact and instant."""
from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

import shadowopt.api.rate_limit as rate_limit

RATE, BURST = 2.0, 3


class Clock:
    def __init__(self):
        self.now = 1000.0

    def monotonic(self):
        return self.now


@pytest.fixture
def limiter(monkeypatch):
    clock = Clock()
    monkeypatch.setattr(rate_limit, "time", SimpleNamespace(monotonic=clock.monotonic))
    return rate_limit.RateLimiter(RATE, BURST), clock


def passes_in_a_row(lim, tenant: str, cap: int = 10_000) -> int:
    n = 0
    while n < cap and lim.take(tenant) == 0.0:
        n += 1
    return n


@pytest.mark.parametrize("idle", [0.0, 0.2, 0.7, 1.2, 1.7, 60.0, 3600.0, 86400.0 * 30])
def test_after_any_idle_time_at_most_burst_requests_pass_at_once(limiter, idle):
    lim, clock = limiter
    assert passes_in_a_row(lim, "alice") == BURST  # a fresh tenant starts with a full bucket
    clock.now += idle
    assert passes_in_a_row(lim, "alice") == min(BURST, math.floor(RATE * idle)), idle
    assert passes_in_a_row(lim, "bob") == BURST  # another tenant's bucket is its own


def test_a_refused_request_is_told_when_a_token_is_back(limiter):
    lim, clock = limiter
    passes_in_a_row(lim, "alice")
    clock.now += 0.2  # 0.4 of a token
    wait = lim.take("alice")
    assert wait == pytest.approx((1 - RATE * 0.2) / RATE)
    clock.now += wait * (1 - 1e-9)
    assert lim.take("alice") > 0  # not yet
    clock.now += wait * 2e-9
    assert lim.take("alice") == 0.0 and lim.take("alice") > 0  # one token, one request


def test_rate_zero_means_no_limit(limiter):
    lim = rate_limit.RateLimiter(0.0, 1)
    assert passes_in_a_row(lim, "alice", cap=500) == 500
