"""Per-client token buckets: what one client may have rendered, so that no stranger starves the rest.

Each client (its address, or the upload token where it shows a valid one) has a bucket of
``burst`` tokens refilled at ``rate`` tokens a second; a request takes its cost (the frame's
pixels, ``costs.FrameLimits.cost``) or is refused with ``RateLimited``, which says how long until
the bucket holds enough (the 429 answer's ``Retry-After``). A request costing more than ``burst``
is priced at ``burst``: it needs a full bucket.

Memory is bounded: a client unseen for as long as an empty bucket takes to refill has a full
bucket, the same as a new one, and is forgotten; beyond ``max_clients`` clients the least
recently seen is forgotten too (it starts again with a full bucket).
"""

import hashlib
import math
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from visnerf_server.settings import Settings

Clock = Callable[[], float]


class RateLimited(Exception):
    """A client asked for more than its bucket holds."""

    def __init__(self, retry_after_s: float, cost: float, available: float) -> None:
        super().__init__(
            f"rate limit: this request costs {cost:.0f} and {available:.0f} are left; "
            f"try again in {retry_after_s:.1f} s"
        )
        self.retry_after_s = retry_after_s
        self.cost = cost
        self.available = available

    @property
    def retry_after_header(self) -> str:
        """Whole seconds (HTTP ``Retry-After``), rounded up so the bucket is full enough by then."""
        return str(max(1, math.ceil(self.retry_after_s - 1e-9)))


@dataclass
class TokenBucket:
    """``tokens`` of at most ``capacity``, refilled at ``rate`` a second since ``updated``."""

    capacity: float
    rate: float
    tokens: float
    updated: float

    def refill(self, now: float) -> None:
        if now > self.updated:
            self.tokens = min(self.capacity, self.tokens + (now - self.updated) * self.rate)
            self.updated = now

    def take(self, cost: float, now: float) -> None:
        """Take ``cost`` tokens (at most ``capacity``) or raise RateLimited, taking none."""
        self.refill(now)
        cost = min(cost, self.capacity)
        if cost > self.tokens:
            raise RateLimited((cost - self.tokens) / self.rate, cost, self.tokens)
        self.tokens -= cost

    @classmethod
    def full(cls, capacity: float, rate: float, now: float) -> "TokenBucket":
        return cls(capacity, rate, capacity, now)

    def try_take(self, cost: float, now: float) -> bool:
        """``take``, answering False (and taking none) instead of raising."""
        try:
            self.take(cost, now)
        except RateLimited:
            return False
        return True

    def wait_s(self, cost: float = 1.0) -> float:
        """Seconds until ``cost`` tokens are there, as of the last refill."""
        return max(0.0, (min(cost, self.capacity) - self.tokens) / self.rate)

    def give_back(self, cost: float) -> None:
        self.tokens = min(self.capacity, self.tokens + min(cost, self.capacity))


class ClientRateLimiter:
    """Token buckets by client key; thread safe."""

    def __init__(self, rate: float, burst: float, max_clients: int = 10_000, clock: Clock = time.monotonic) -> None:
        if rate <= 0 or burst <= 0 or max_clients < 1:
            raise ValueError("rate and burst must be positive and max_clients >= 1, "
                             f"got {rate}, {burst}, {max_clients}")
        self.rate = rate
        self.burst = float(burst)
        self.max_clients = max_clients
        self._clock = clock
        self._buckets: OrderedDict[str, TokenBucket] = OrderedDict()
        """Least recently seen first."""
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._buckets)

    def take(self, client: str, cost: float) -> None:
        """Charge ``client`` ``cost`` tokens; raises RateLimited (nothing charged) when it lacks them."""
        with self._lock:
            now = self._clock()
            self._forget_idle(now)
            bucket = self._buckets.get(client)
            if bucket is None:
                bucket = TokenBucket(self.burst, self.rate, self.burst, now)
                self._buckets[client] = bucket
                while len(self._buckets) > self.max_clients:
                    self._buckets.popitem(last=False)
            else:
                self._buckets.move_to_end(client)
            bucket.take(cost, now)

    def give_back(self, client: str, cost: float) -> None:
        """Return tokens a request took but did not use (it was refused before rendering)."""
        with self._lock:
            bucket = self._buckets.get(client)
            if bucket is not None:
                bucket.give_back(cost)

    def _forget_idle(self, now: float) -> None:
        """Forget the clients unseen for ``burst / rate`` seconds: their buckets are full again,
        the same as new ones. Least recently seen first, so the scan stops at the first one seen
        since (amortised: each client is forgotten once per visit)."""
        refill_s = self.burst / self.rate
        while self._buckets:
            client, bucket = next(iter(self._buckets.items()))
            if now - bucket.updated < refill_s:
                return
            del self._buckets[client]


def limiter_from_settings(settings: Settings) -> ClientRateLimiter | None:
    """The server's limiter (``rate_limit_*`` settings); None when the rate is 0 (no limit)."""
    if settings.rate_limit_pixels_per_s <= 0:
        return None
    return ClientRateLimiter(
        settings.rate_limit_pixels_per_s, settings.rate_limit_burst_pixels, settings.rate_limit_clients
    )


def client_key(host: str | None, authorization: str | None, token: str | None) -> str:
    """The rate-limit key of a request: ``token:...`` when it carries ``Authorization: Bearer``
    with the server's upload token (a trusted client keeps its own bucket wherever it connects
    from), else ``addr:<client address>``."""
    if token and authorization:
        scheme, _, presented = authorization.strip().partition(" ")
        if scheme.lower() == "bearer" and secrets.compare_digest(presented.strip().encode(), token.encode()):
            return "token:" + hashlib.sha256(token.encode()).hexdigest()[:16]
    return f"addr:{host or 'unknown'}"
