"""Admission control for the heavy requests (upload loads, optimize, evaluate, compare, batch creation).

Everything here runs on the event loop and never blocks a thread:
- `Admission.admit(tenant)` answers at once: a refusal (429 when this tenant has `tenant_max_inflight` in;
  503 when `max_inflight` heavy requests are in and this tenant has one of them) or a ticket that counts
  the request as in flight until it is released (queued and running requests alike:
  `shadowopt_inflight_requests`; a batch results download too, while it streams). Headroom: a tenant
  with no request in flight is always admitted, so two tenants at their quota cannot lock a third out;
  the total can exceed `max_inflight` by at most the number of tenants (one request each);
- a ticket then waits for a slot of a `FairPool` (solver slots, `solve_threads`; scene-load slots,
  `load_threads`; batch result downloads, `download_threads`, held while the response streams) as an
  asyncio future. A freed slot goes to the waiting tenant that holds the fewest slots
  of the pool, ties taken in turn (round robin over the tenants with waiting requests, FIFO within a
  tenant): one tenant's 40 waiting requests do not all go before another tenant's one, and a tenant that
  arrives while another holds every slot gets the next one; while another tenant is active, no tenant holds
  every slot of a pool of two or more (one is kept for the others). Only a request holding a slot takes a
  worker thread;
- a ticket that `watch`es its request's ASGI `receive` notices the client going away (http.disconnect):
  a wait for a slot (`Ticket.slot`, `Ticket.wait`) then ends at once with `ClientGone`, the ticket is
  released by the route leaving, and a request whose client left before it got its slot never runs.
"""
from __future__ import annotations

import asyncio
import contextlib
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field


class Refused(Exception):
    """An admission refusal: the HTTP status, error code, message and Retry-After seconds."""

    def __init__(self, status: int, code: str, message: str, retry_after: int = 1):
        super().__init__(message)
        self.status, self.code, self.message, self.retry_after = status, code, message, retry_after


class ClientGone(Exception):
    """The client disconnected while its request waited: the request is dropped without running."""


class FairPool:
    """`size` slots handed out on the event loop, shared fairly between tenants.

    A freed slot goes to the waiting tenant holding the fewest slots (the tenant just served last among
    equals). While another tenant is active (holds a slot, waits, or asked within `recent_s` seconds), no
    tenant may hold more than `size - 1` slots of a pool of two or more: one slot stays for the others, so a
    tenant sending requests one after another never waits behind a flood of another tenant's running work.
    """

    def __init__(self, name: str, size: int, recent_s: float = 5.0):
        self.name, self.size, self.recent_s = name, size, recent_s
        self.busy = 0
        self.held: dict[str, int] = {}  # tenant -> slots it holds
        self.waiting = 0  # requests waiting for a slot (kept as a count: /metrics reads it from another thread)
        self._waiting: OrderedDict[str, deque[asyncio.Future]] = OrderedDict()  # tenant -> its waiters, in turn
        self._seen: dict[str, float] = {}  # tenant -> when it last asked for a slot (time.monotonic)
        self._timer: asyncio.TimerHandle | None = None

    def _others_active(self, tenant: str, now: float) -> bool:
        return any(t != tenant and (self.held.get(t) or t in self._waiting or now - seen < self.recent_s)
                   for t, seen in self._seen.items())

    def _may_take(self, tenant: str, now: float) -> bool:
        cap = self.size - 1 if self.size > 1 and self._others_active(tenant, now) else self.size
        return self.held.get(tenant, 0) < cap

    def _grant(self, tenant: str) -> None:
        self.busy += 1
        self.held[tenant] = self.held.get(tenant, 0) + 1

    async def acquire(self, tenant: str) -> None:
        now = time.monotonic()
        self._seen[tenant] = now
        if self.busy < self.size and not self._waiting and self._may_take(tenant, now):
            self._grant(tenant)
            return
        fut = asyncio.get_running_loop().create_future()
        self._waiting.setdefault(tenant, deque()).append(fut)
        self.waiting += 1
        self._dispatch()
        try:
            await fut
        except asyncio.CancelledError:
            if fut.done() and not fut.cancelled():  # handed a slot and cancelled at the same time: give it on
                self.release(tenant)
            else:
                q = self._waiting.get(tenant)
                if q is not None and fut in q:
                    q.remove(fut)
                    self.waiting -= 1
                    if not q:
                        del self._waiting[tenant]
                self._dispatch()
            raise

    def release(self, tenant: str) -> None:
        """`tenant` frees a slot; it goes on to the next waiter that may take it (see the class)."""
        left = self.held.get(tenant, 1) - 1
        if left > 0:
            self.held[tenant] = left
        else:
            self.held.pop(tenant, None)
        self.busy -= 1
        if tenant in self._waiting:  # the tenant just served goes behind the others among equals
            self._waiting.move_to_end(tenant)
        self._dispatch()

    def _dispatch(self) -> None:
        """Hand free slots to waiters: fewest slots held first, first in turn among equals (who then goes to
        the back of the line). A slot kept for other tenants is handed out once they have been idle for
        `recent_s` (a timer looks again then)."""
        now = time.monotonic()
        while self.busy < self.size and self._waiting:
            eligible = [t for t in self._waiting if self._may_take(t, now)]
            if not eligible:
                if self._timer is None:  # look again when the most recent other tenant's activity ages out
                    ages_out = [seen + self.recent_s - now for seen in self._seen.values() if now - seen < self.recent_s]
                    delay = max(0.01, min(ages_out, default=self.recent_s))
                    self._timer = asyncio.get_running_loop().call_later(delay, self._wake)
                return
            nxt = min(eligible, key=lambda t: self.held.get(t, 0))  # min keeps the first of equals
            q = self._waiting.pop(nxt)
            fut = q.popleft()
            self.waiting -= 1
            if q:
                self._waiting[nxt] = q  # to the back of the line
            if not fut.done():
                fut.set_result(None)
                self._grant(nxt)
        self._forget(now)

    def _wake(self) -> None:
        self._timer = None
        self._dispatch()

    def _forget(self, now: float) -> None:
        """Drop tenants that hold nothing, wait for nothing and were last seen long ago (bounded memory)."""
        if len(self._seen) > 64:
            for t in [t for t, seen in self._seen.items() if now - seen > self.recent_s
                      and not self.held.get(t) and t not in self._waiting]:
                del self._seen[t]

    @contextlib.asynccontextmanager
    async def slot(self, tenant: str):
        await self.acquire(tenant)
        try:
            yield
        finally:
            self.release(tenant)


@dataclass
class Ticket:
    tenant: str
    admission: "Admission"
    released: bool = field(default=False)
    gone: asyncio.Event | None = field(default=None)  # set once the client has disconnected (when watched)
    _watcher: asyncio.Task | None = field(default=None, repr=False)

    def watch(self, receive) -> None:
        """Watch the request's ASGI `receive` for http.disconnect. Call it once the request body has been
        read (the watcher consumes messages; after the body the only one left is the disconnect)."""
        if self._watcher is not None:
            return
        self.gone = gone = asyncio.Event()

        async def watcher():
            while True:
                message = await receive()
                if message is None or message.get("type") == "http.disconnect":
                    gone.set()
                    return

        self._watcher = asyncio.get_running_loop().create_task(watcher())

    @property
    def client_gone(self) -> bool:
        return self.gone is not None and self.gone.is_set()

    async def wait(self, aw):
        """`await aw`, unless the client disconnects first: then `aw` is cancelled and ClientGone raised."""
        if self.gone is None:
            return await aw
        task = asyncio.ensure_future(aw)
        gone = asyncio.ensure_future(self.gone.wait())
        try:
            await asyncio.wait({task, gone}, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:
            task.cancel()
            raise
        finally:
            gone.cancel()
        if task.done():
            return task.result()
        task.cancel()  # FairPool.acquire gives back a slot it was handed at the same moment
        with contextlib.suppress(asyncio.CancelledError):
            await task
        raise ClientGone()

    @contextlib.asynccontextmanager
    async def slot(self, pool: FairPool):
        """A slot of `pool` for this ticket's tenant; ClientGone when the client left before it was given
        (a request whose client is gone never starts its work)."""
        await self.wait(pool.acquire(self.tenant))
        try:
            if self.client_gone:
                raise ClientGone()
            yield
        finally:
            pool.release(self.tenant)

    def release(self) -> None:
        if self._watcher is not None:
            self._watcher.cancel()
            self._watcher = None
        if not self.released:
            self.released = True
            self.admission._release(self.tenant)


class Admission:
    """Counts heavy requests in flight (total and per tenant) and owns the slot pools."""

    def __init__(self, max_inflight: int, tenant_max_inflight: int, solve_threads: int, load_threads: int,
                 download_threads: int = 2):
        self.max_inflight, self.tenant_max_inflight = max_inflight, tenant_max_inflight
        self.inflight = 0
        self.by_tenant: dict[str, int] = {}
        self.solve = FairPool("solve", solve_threads)
        self.load = FairPool("load", load_threads)
        self.download = FairPool("download", download_threads)  # batch result streams (held while they stream)

    def admit(self, tenant: str) -> Ticket:
        """A ticket, or Refused at once (nothing waits here). A tenant with nothing in flight is always
        admitted (headroom: `max_inflight` only refuses tenants that already have a request in)."""
        mine = self.by_tenant.get(tenant, 0)
        if mine >= self.tenant_max_inflight:
            raise Refused(429, "tenant_quota", f"this token has {mine} heavy requests in flight, the per-tenant "
                          f"quota tenant_max_inflight = {self.tenant_max_inflight}; retry when one has finished")
        if self.inflight >= self.max_inflight and mine > 0:
            raise Refused(503, "busy", f"{self.inflight} heavy requests are in flight (server limit "
                          f"max_inflight = {self.max_inflight}) and this token has {mine} of them; retry shortly")
        self.inflight += 1
        self.by_tenant[tenant] = mine + 1
        return Ticket(tenant, self)

    def _release(self, tenant: str) -> None:
        self.inflight -= 1
        left = self.by_tenant.get(tenant, 1) - 1
        if left > 0:
            self.by_tenant[tenant] = left
        else:
            self.by_tenant.pop(tenant, None)

    @contextlib.asynccontextmanager
    async def heavy(self, tenant: str):
        ticket = self.admit(tenant)
        try:
            yield ticket
        finally:
            ticket.release()
