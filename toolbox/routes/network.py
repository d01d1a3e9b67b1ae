"""The route network (seeds/image-based-route-maps.txt, sec. 3.4): routes joined where their places
look alike, and the way through them from one place to another. I/O free.

Nodes are places (route, index): place i of a route is the image before its leg i, place n its
last image after. A leg joins places i and i + 1 both ways (forward as taught, backward by the
reversed action); a link joins two places of different routes that are the same place. Costs are
metres driven, a turn counting as `turn_cost_m` per radian and a link as `link_cost_m` (its
adjustment), so the way found is the shortest drive through the network.
"""
from __future__ import annotations

import heapq
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

Place = tuple[str, int]


@dataclass(frozen=True)
class NetworkLeg:
    route: str
    index: int          # the leg's index on its route
    kind: str           # forward | backward | turn
    value: float


@dataclass(frozen=True)
class NetworkLink:
    a: Place
    b: Place


@dataclass(frozen=True)
class Segment:
    """A stretch of one route: from place `start` to place `end` (end < start: followed backward)."""

    route: str
    start: int
    end: int

    @property
    def reverse(self) -> bool:
        return self.end < self.start


def leg_cost(kind: str, value: float, turn_cost_m: float) -> float:
    return abs(value) * turn_cost_m if kind == "turn" else abs(value)


def shortest_way(legs: Iterable[NetworkLeg], links: Iterable[NetworkLink], start: Place, goal: Place,
                 turn_cost_m: float = 0.3, link_cost_m: float = 0.5) -> tuple[list[Segment], float] | None:
    """The cheapest way from start to goal as route segments, and its cost; None if unconnected."""
    graph: dict[Place, list[tuple[Place, float]]] = {}

    def join(a: Place, b: Place, cost: float) -> None:
        graph.setdefault(a, []).append((b, cost))
        graph.setdefault(b, []).append((a, cost))

    for leg in legs:
        join((leg.route, leg.index), (leg.route, leg.index + 1), leg_cost(leg.kind, leg.value, turn_cost_m))
    for link in links:
        join(link.a, link.b, link_cost_m)
    if start not in graph or goal not in graph:
        return ([], 0.0) if start == goal else None
    best: dict[Place, float] = {start: 0.0}
    came: dict[Place, Place] = {}
    queue = [(0.0, start)]
    while queue:
        cost, place = heapq.heappop(queue)
        if place == goal:
            break
        if cost > best[place]:
            continue
        for nxt, step in graph[place]:
            if cost + step < best.get(nxt, float("inf")):
                best[nxt], came[nxt] = cost + step, place
                heapq.heappush(queue, (cost + step, nxt))
    if goal not in best:
        return None
    path = [goal]
    while path[-1] != start:
        path.append(came[path[-1]])
    return segments(path[::-1]), best[goal]


def segments(path: Sequence[Place]) -> list[Segment]:
    """Places in order into stretches of one route each (a link starts a new stretch)."""
    out: list[Segment] = []
    for a, b in zip(path[:-1], path[1:], strict=True):
        if a[0] != b[0]:
            continue                                   # a link: the next stretch starts at b
        if out and out[-1].route == a[0] and out[-1].end == a[1] and (b[1] - a[1]) == (1 if not out[-1].reverse
                                                                                       else -1):
            out[-1] = Segment(a[0], out[-1].start, b[1])
        else:
            out.append(Segment(a[0], a[1], b[1]))
    return out
