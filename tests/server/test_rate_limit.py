"""Per-client token buckets (``rate_limit``) on a fake clock: the refusal and its Retry-After, one
bucket per client, a trusted token's own bucket, forgetting idle clients, thread safety."""

import threading

import pytest

from visnerf_server.rate_limit import ClientRateLimiter, RateLimited, TokenBucket, client_key


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_over_the_limit_is_refused_with_the_time_until_enough_is_back() -> None:
    clock = FakeClock()
    limiter = ClientRateLimiter(rate=100.0, burst=1000.0, clock=clock)
    limiter.take("a", 900.0)
    with pytest.raises(RateLimited) as refused:
        limiter.take("a", 350.0)  # 100 left, 250 short at 100 a second: 2.5 s
    assert refused.value.retry_after_s == pytest.approx(2.5)
    assert refused.value.retry_after_header == "3"  # whole seconds, rounded up
    assert refused.value.cost == 350.0 and refused.value.available == pytest.approx(100.0)
    clock.now += 2.49
    with pytest.raises(RateLimited) as again:
        limiter.take("a", 350.0)  # a refusal took nothing: still just short
    assert again.value.retry_after_s == pytest.approx(0.01)
    assert again.value.retry_after_header == "1"
    clock.now += 0.01
    limiter.take("a", 350.0)  # exactly when it said
    with pytest.raises(RateLimited):
        limiter.take("a", 1.0)


def test_a_request_over_the_burst_needs_a_full_bucket() -> None:
    clock = FakeClock()
    limiter = ClientRateLimiter(rate=10.0, burst=100.0, clock=clock)
    limiter.take("a", 5000.0)  # priced at the burst
    with pytest.raises(RateLimited) as refused:
        limiter.take("a", 5000.0)
    assert refused.value.retry_after_s == pytest.approx(10.0)
    clock.now += 10.0
    limiter.take("a", 5000.0)


def test_clients_have_their_own_buckets_and_refunds_return_tokens() -> None:
    clock = FakeClock()
    limiter = ClientRateLimiter(rate=1.0, burst=10.0, clock=clock)
    limiter.take("a", 10.0)
    limiter.take("b", 10.0)  # a's spending is not b's
    with pytest.raises(RateLimited):
        limiter.take("a", 1.0)
    limiter.give_back("a", 4.0)
    limiter.take("a", 4.0)
    limiter.give_back("a", 50.0)  # never above the burst
    limiter.take("a", 10.0)
    with pytest.raises(RateLimited):
        limiter.take("a", 1.0)


def test_idle_clients_are_forgotten_and_the_count_is_bounded() -> None:
    clock = FakeClock()
    limiter = ClientRateLimiter(rate=10.0, burst=100.0, max_clients=50, clock=clock)  # refills in 10 s
    for i in range(40):
        limiter.take(f"c{i}", 100.0)
    assert len(limiter) == 40
    clock.now += 9.5
    limiter.take("late", 1.0)
    assert len(limiter) == 41  # none has refilled yet: each still owes
    clock.now += 0.5
    limiter.take("later", 1.0)
    assert len(limiter) == 2  # the 40 are full again, the same as new: forgotten
    limiter.take("c0", 100.0)  # and start with a full bucket
    for i in range(200):
        limiter.take(f"flood{i}", 1.0)
    assert len(limiter) == 50  # past max_clients the least recently seen go


def test_concurrent_takes_never_spend_more_than_the_bucket_holds() -> None:
    limiter = ClientRateLimiter(rate=1e-6, burst=1000.0, clock=FakeClock())
    granted = []
    lock = threading.Lock()

    def spend() -> None:
        for _ in range(100):
            try:
                limiter.take("shared", 3.0)
            except RateLimited:
                continue
            with lock:
                granted.append(1)

    threads = [threading.Thread(target=spend) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(granted) == 333


def test_client_key_uses_the_token_only_when_it_is_the_servers() -> None:
    token = "s3cret-token"
    assert client_key("10.0.0.1", None, token) == "addr:10.0.0.1"
    assert client_key("10.0.0.1", "Bearer wrong", token) == "addr:10.0.0.1"
    assert client_key("10.0.0.1", "Basic s3cret-token", token) == "addr:10.0.0.1"
    trusted = client_key("10.0.0.1", "Bearer s3cret-token", token)
    assert trusted.startswith("token:") and token not in trusted
    assert client_key("10.9.9.9", "bearer  s3cret-token ", token) == trusted  # wherever it connects from
    assert client_key(None, None, token) == "addr:unknown"


def test_limits_must_be_positive() -> None:
    with pytest.raises(ValueError, match="positive"):
        ClientRateLimiter(rate=0.0, burst=10.0)


def test_a_bucket_of_messages_takes_one_at_a_time_and_says_the_wait() -> None:
    bucket = TokenBucket.full(3.0, 2.0, now=0.0)  # the stream's: 3 at once, then 2 a second
    assert [bucket.try_take(1.0, 0.0) for _ in range(4)] == [True, True, True, False]
    assert bucket.wait_s() == pytest.approx(0.5) and bucket.tokens == 0.0  # the refusal took nothing
    assert not bucket.try_take(1.0, 0.4) and bucket.wait_s() == pytest.approx(0.1)
    assert bucket.try_take(1.0, 0.5)
    assert bucket.try_take(1.0, 10.0) and bucket.tokens == pytest.approx(2.0)  # refilled to 3, at most
