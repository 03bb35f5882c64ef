"""Cutting the view graph (images joined by verified pairs, weighted by their inliers)
into overlapping clusters: recursive bisection, then each cluster grown by the outside
images most connected to it."""

from __future__ import annotations

from collections import deque

from colmap_ext.database import DatabaseContents
from colmap_ext.hierarchical_mapper.options import HierarchicalOptions


def view_graph(db: DatabaseContents, min_num_inliers: int) -> dict[int, dict[int, int]]:
    """image id -> {neighbour id: verified inliers}, every image a node; the raw matches
    stand in for a database without two-view geometries (the mapper verifies them)."""
    graph: dict[int, dict[int, int]] = {image_id: {} for image_id in db.images}
    for (id1, id2), matches in (db.verified_matches or db.raw_matches).items():
        if len(matches) >= min_num_inliers:
            graph[id1][id2] = graph[id2][id1] = len(matches)
    return graph


def components(graph: dict[int, dict[int, int]], nodes: list[int]) -> list[list[int]]:
    """Connected components of the subgraph on `nodes`, largest first."""
    inside, seen, found = set(nodes), set(), []
    for start in sorted(nodes):
        if start in seen:
            continue
        seen.add(start)
        component, queue = [], deque([start])
        while queue:
            node = queue.popleft()
            component.append(node)
            for other in graph[node]:
                if other in inside and other not in seen:
                    seen.add(other)
                    queue.append(other)
        found.append(sorted(component))
    return sorted(found, key=len, reverse=True)


def breadth_first_order(graph: dict[int, dict[int, int]], nodes: set[int], start: int) -> list[int]:
    """`nodes` reachable from `start` in breadth-first order, the stronger edges first."""
    order, seen, queue = [], {start}, deque([start])
    while queue:
        node = queue.popleft()
        order.append(node)
        for other in sorted(graph[node], key=lambda o: (-graph[node][o], o)):
            if other in nodes and other not in seen:
                seen.add(other)
                queue.append(other)
    return order


def bisect(graph: dict[int, dict[int, int]], nodes: list[int]) -> tuple[list[int], list[int]]:
    """Two halves of a connected set: breadth-first levels from a pseudo-peripheral image
    (the far end of a search from the far end of a search, as in George and Liu's
    ordering), cut at the middle. On sequences, rings and grids the halves are
    contiguous stretches, and the cut crosses few edges; linear time."""
    inside = set(nodes)
    far = breadth_first_order(graph, inside, nodes[0])[-1]
    order = breadth_first_order(graph, inside, far)
    order = order + sorted(inside - set(order))  # (connected: nothing is left)
    middle = len(order) // 2
    return sorted(order[:middle]), sorted(order[middle:])


def leaf_clusters(graph: dict[int, dict[int, int]], nodes: list[int],
                  max_size: int) -> list[list[int]]:
    """Recursive bisection into connected clusters of at most `max_size` images."""
    leaves, stack = [], [nodes]
    while stack:
        cluster = stack.pop()
        if len(cluster) <= max_size:
            leaves.append(cluster)
            continue
        for half in bisect(graph, cluster):
            stack.extend(components(graph, half))
    return sorted(leaves, key=lambda c: c[0])


def grow(graph: dict[int, dict[int, int]], leaf: list[int], leaf_of: dict[int, int],
         overlap: int) -> list[int]:
    """The leaf and `overlap` outside images, shared out among the leaves it links to
    (`leaf_of`: image id -> its leaf): each gives in turn its next image with most
    inliers to this leaf, the most linked leaf first. Every junction gets its share:
    the `overlap` images most linked to the leaf, whatever their leaf, can leave a
    junction of a sequence with few or none where the other side links more (a turn on
    one side, a stop on the other), and the chain of models breaks there."""
    members = set(leaf)
    links: dict[int, int] = {}
    for node in members:
        for other, weight in graph[node].items():
            if other not in members:
                links[other] = links.get(other, 0) + weight
    by_leaf: dict[int, list[int]] = {}
    for other in sorted(links, key=lambda o: (-links[o], o)):
        by_leaf.setdefault(leaf_of[other], []).append(other)
    strength = {k: sum(links[o] for o in images) for k, images in by_leaf.items()}
    turns = sorted(((rank, -strength[k], k, image) for k, images in by_leaf.items()
                    for rank, image in enumerate(images)))
    return sorted(members | {image for *_, image in turns[:overlap]})


def partition(db: DatabaseContents, options: HierarchicalOptions) -> list[list[int]]:
    """Overlapping clusters of image ids covering every image with a verified pair."""
    graph = view_graph(db, options.min_num_inliers)
    connected = [c for c in components(graph, list(graph)) if len(c) >= 2]
    clusters = []
    for component in connected:
        leaves = leaf_clusters(graph, component, options.leaf_max_num_images)
        leaf_of = {image: index for index, leaf in enumerate(leaves) for image in leaf}
        clusters += [grow(graph, leaf, leaf_of, options.image_overlap) for leaf in leaves]
    return clusters
