"""
A time-indexed tree of rigid transforms, as tf2 keeps one, and pose streams through it.

Edges are parent -> child transforms T_parent_child (pose.Pose, quaternion (w, x, y, z));
stamps are integer nanoseconds; each frame has at most one parent.  A static edge holds one
transform valid at all times.  A dynamic edge buffers its stamped transforms (a
pose_buffer.PoseBuffer: the last `cache_ns` of stamps, at most `max_length`, late ones
inserted in order) and is evaluated between the two stamps that bracket the requested one:
position linearly, rotation by SLERP (pose_buffer.interpolate_pose).  Never extrapolated,
never across a gap longer than `max_gap_ns`.

`TransformTree.chain(target, source)` finds the edges from `target` up to the common ancestor
and down to `source`; `TransformTree.lookup(target, source, stamp_ns)` composes T_target_source.
`FramePoses` turns the tree into a pose stream: T_target_source at each stamp at which a
dynamic transform on the chain arrived, as soon as the whole chain can be evaluated there.

A dynamic stamp more than `time_jump_ns` older than its edge's newest (a bag played again)
clears every dynamic buffer, as tf2 does when time jumps back; static edges are kept.
Core module: standard library and numpy only.
"""

import bisect
from collections import Counter
from typing import NamedTuple

from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.stream.pose_buffer import LATER, OLDER, PoseBuffer

# Lookup outcomes: evaluated; not yet (an edge has no transform at or after the stamp);
# never (the stamp is older than a buffer, or inside a gap too long to interpolate across).
READY, WAIT, NEVER = 'ready', 'wait', 'never'


class TreeError(ValueError):
    """A transform that would break the tree (a loop, or an edge from a frame to itself)."""


class Chain(NamedTuple):
    """
    The edges between two frames: `steps` from target to source, each (child, inverted).

    An edge is named by its child frame.  Composing the steps' transforms in order, each
    inverted when `inverted`, gives T_target_source.
    """

    target: str
    source: str
    steps: tuple

    @property
    def children(self):
        """Return the child frames of the chain's edges (a frozenset)."""
        return frozenset(child for child, _ in self.steps)


class _Edge:
    """One parent -> child edge: a static transform, or a PoseBuffer of stamped ones."""

    def __init__(self, parent, static, cache_ns, max_length):
        self.parent = parent
        self.static = static
        self.static_pose = None
        self.transforms = PoseBuffer(cache_ns, max_length)

    def at(self, stamp_ns, max_gap_ns):
        """(READY, pose) at stamp_ns, or (WAIT or NEVER, why)."""
        if self.static:
            return READY, self.static_pose
        pose, miss = self.transforms.at(stamp_ns, max_gap_ns)
        if miss is None:
            return READY, pose
        if miss.reason == LATER:
            return WAIT, 'no transform at or after the stamp yet'
        if miss.reason == OLDER:
            return NEVER, 'stamp older than the buffered transforms'
        return NEVER, f'gap of {(miss.after_ns - miss.before_ns) / NS_PER_S:.3g} s'


def normalize_frame(frame):
    """Return a frame id without tf2's forbidden leading slash ('/base' -> 'base')."""
    return str(frame).lstrip('/')


def frame_problem(frame):
    """
    Say why TF cannot take `frame` as a result's frame id, or return ''.

    Empty (a lone '/'), or with a space or a control character: such a name went into the
    static_transform_publisher line, the URDF joint and the files.
    """
    name = normalize_frame(frame)
    if name and name.isprintable() and not any(c.isspace() for c in name):
        return ''
    return (f'{str(frame)!r} is not a frame TF can take (empty, or with a space or a control '
            'character)')


class TransformTree:
    """Static and buffered dynamic transforms between frames (module docstring)."""

    def __init__(self, cache_ns=10 * NS_PER_S, max_gap_ns=None, max_length=100_000,
                 time_jump_ns=NS_PER_S // 2):
        if cache_ns <= 0 or max_length < 2 or time_jump_ns < 0:
            raise ValueError('need cache_ns > 0, max_length >= 2 and time_jump_ns >= 0')
        if max_gap_ns is not None and max_gap_ns <= 0:
            raise ValueError(f'max_gap_ns must be positive (or None), not {max_gap_ns}')
        self.cache_ns = int(cache_ns)
        self.max_gap_ns = max_gap_ns
        self.max_length = int(max_length)
        self.time_jump_ns = int(time_jump_ns)
        self._edges = {}          # child frame -> _Edge
        self._chains = {}         # (target, source) -> Chain or None, while the tree holds
        self.generation = 0       # counts the clears after time jumps
        self.stale = Counter()    # transforms older than their buffer: not stored

    @property
    def frames(self):
        """Return every frame the tree knows (a set)."""
        return set(self._edges) | {edge.parent for edge in self._edges.values()}

    def frames_without(self, children):
        """Return the frames of every edge but those that hold `children` (a set of frames)."""
        return {frame for child, edge in self._edges.items() if child not in children
                for frame in (child, edge.parent)}

    def parent(self, frame):
        """Return the parent of `frame`, or None for a root or an unknown frame."""
        edge = self._edges.get(normalize_frame(frame))
        return edge.parent if edge else None

    def is_static(self, frame):
        """Return whether `frame` hangs from its parent by a static transform."""
        edge = self._edges.get(normalize_frame(frame))
        return bool(edge and edge.static)

    def set_transform(self, parent, child, stamp_ns, pose, static=False, keep=False):
        """
        Add T_parent_child (pose.Pose) at stamp_ns (int); return whether it was stored.

        Raises TreeError for a loop.  A new parent for a known child replaces the edge.  A
        dynamic transform of a static edge sets its value and it stays static, as in tf2 (an
        edge on /tf_static that a driver also sends once on /tf once lost its static value:
        no pose composed before that stamp, or across the gaps of a slow republisher).
        keep: a child that hangs from a static edge keeps it (a recording's first value).
        """
        parent, child = normalize_frame(parent), normalize_frame(child)
        edge = self._edges.get(child)
        if keep and static and edge is not None and edge.static:
            return True
        if edge is None or edge.parent != parent or (static and not edge.static):
            edge = self._new_edge(parent, child, static)
        if edge.static:
            edge.static_pose = pose
            return True
        stamp_ns = int(stamp_ns)
        newest_ns = edge.transforms.newest_ns
        if newest_ns is not None and newest_ns - stamp_ns > self.time_jump_ns:
            self.clear_dynamic()
        if edge.transforms.insert(stamp_ns, pose):
            edge.transforms.trim()
            return True
        self.stale[child] += 1
        return False

    def _new_edge(self, parent, child, static):
        if parent == child:
            raise TreeError(f'transform from frame {child!r} to itself')
        frame = parent
        while frame is not None:
            if frame == child:
                raise TreeError(f'{parent!r} -> {child!r} would close a loop: {parent!r} '
                                f'already descends from {child!r}')
            frame = self.parent(frame)
        edge = self._edges[child] = _Edge(parent, static, self.cache_ns, self.max_length)
        self._chains.clear()
        return edge

    def remove_edge(self, child):
        """Forget the edge that holds `child` (a transform its publisher has replaced)."""
        if self._edges.pop(normalize_frame(child), None) is not None:
            self._chains.clear()

    def clear_dynamic(self):
        """Forget every dynamic transform (time jumped back); static ones stay."""
        for edge in self._edges.values():
            if not edge.static:
                edge.transforms.clear()
        self.generation += 1

    def path_to_root(self, frame):
        """Return [frame, its parent, ..., the root] (just [frame] for an unknown frame)."""
        frame = normalize_frame(frame)
        path = [frame]
        while frame in self._edges:
            frame = self._edges[frame].parent
            path.append(frame)
        return path

    def disconnection(self, target, source):
        """
        Say why frames `target` and `source` are not connected.

        Which of them is in no transform received, or the roots of their two separate trees.
        """
        target, source = normalize_frame(target), normalize_frame(source)
        known = self.frames
        missing = [frame for frame in (target, source) if frame not in known]
        if missing:
            return (f'{" and ".join(missing)} {"is" if len(missing) == 1 else "are"} in no '
                    'transform received')
        roots = [self.path_to_root(frame)[-1] for frame in (target, source)]
        return (f'they are in two separate trees ({target} hangs from root {roots[0]}, '
                f'{source} from root {roots[1]}): no transform joins them')

    def chain(self, target, source):
        """Return the Chain from frame `target` to frame `source`, or None if not connected."""
        key = (normalize_frame(target), normalize_frame(source))
        if key not in self._chains:
            self._chains[key] = self._find_chain(*key)
        return self._chains[key]

    def _find_chain(self, target, source):
        up_target = self.path_to_root(target)
        up_source = self.path_to_root(source)
        ancestors = set(up_target)
        common = next((frame for frame in up_source if frame in ancestors), None)
        if common is None:
            return None
        up = up_target[:up_target.index(common)]
        down = up_source[:up_source.index(common)]
        steps = [(frame, True) for frame in up] + [(frame, False) for frame in reversed(down)]
        return Chain(target, source, tuple(steps))

    def evaluate(self, chain, stamp_ns):
        """(READY, T_target_source) at stamp_ns, or (WAIT or NEVER, why) naming the edge."""
        result = None
        waiting = None
        for child, inverted in chain.steps:
            edge = self._edges[child]
            status, value = edge.at(stamp_ns, self.max_gap_ns)
            if status == NEVER:
                return NEVER, f'{edge.parent} -> {child}: {value}'
            if status == WAIT:
                waiting = waiting or f'{edge.parent} -> {child}: {value}'
                continue
            if waiting is None:
                step = value.inverse() if inverted else value
                result = step if result is None else result @ step
        if waiting is not None:
            return WAIT, waiting
        return READY, Pose.identity() if result is None else result

    def lookup(self, target, source, stamp_ns):
        """
        Return T_target_source (pose.Pose) at stamp_ns.

        Raises LookupError saying why (frames not connected, no transform yet, gap, too old).
        """
        chain = self.chain(target, source)
        if chain is None:
            raise LookupError(f'frames {target!r} and {source!r} are not connected')
        status, value = self.evaluate(chain, int(stamp_ns))
        if status != READY:
            raise LookupError(f'{target} -> {source} at {stamp_ns} ns: {value}')
        return value


class FramePoses:
    """
    T_target_source at the stamps where a dynamic transform on its chain arrived.

    Call `note(child, stamp_ns)` after each dynamic TransformTree.set_transform, then `ready()`
    for the poses that can now be evaluated, oldest first and with increasing stamps.  Stamps
    that can never be evaluated are counted in `dropped` (by reason) with `last_dropped`, the
    latest explanation; at most `max_pending` stamps wait.
    """

    def __init__(self, tree, target, source, max_pending=10_000):
        self.tree = tree
        self.target = normalize_frame(target)
        self.source = normalize_frame(source)
        self.max_pending = max_pending
        self.dropped = Counter()
        self.last_dropped = ''
        self._pending = []
        self._last_ns = None
        self._generation = tree.generation

    @property
    def pending(self):
        """Return the number of stamps waiting for transforms."""
        return len(self._pending)

    @property
    def static_chain(self):
        """Return whether the frames are joined by static transforms alone (no pose moves)."""
        chain = self.tree.chain(self.target, self.source)
        return chain is not None and all(self.tree.is_static(child) for child, _ in chain.steps)

    def note(self, child, stamp_ns):
        """Record that edge `child` got a dynamic transform at stamp_ns."""
        self._check_generation()
        child = normalize_frame(child)
        chain = self.tree.chain(self.target, self.source)
        if chain is None:
            # Count only transforms that lead towards one of the two frames.
            if child in self.tree.path_to_root(self.target) + self.tree.path_to_root(self.source):
                self._drop('frames not connected', f'{self.target} and {self.source} are not '
                           'connected in the transform tree: '
                           + self.tree.disconnection(self.target, self.source))
            return
        if child not in chain.children:
            return
        if self._last_ns is not None and stamp_ns <= self._last_ns:
            if stamp_ns < self._last_ns:   # every edge had moved past it: it came too late
                self._drop('out of order', f'a transform to {child} came '
                           f'{(self._last_ns - stamp_ns) * 1e-6:.3g} ms older than the last '
                           f'{self.target} -> {self.source} pose composed')
            return   # (at the stamp just evaluated: another edge's share of it)
        pending = self._pending
        if not pending or stamp_ns > pending[-1]:
            pending.append(stamp_ns)
        else:
            index = bisect.bisect_left(pending, stamp_ns)
            if pending[index] != stamp_ns:
                pending.insert(index, stamp_ns)
        if len(pending) > self.max_pending:
            self._drop('waiting too long', f'more than {self.max_pending} stamps waited for '
                       f'transforms on {self.target} -> {self.source}')
            del pending[0]

    def ready(self):
        """Return [(stamp_ns, T_target_source)] now evaluable, oldest first."""
        self._check_generation()
        out = []
        chain = self.tree.chain(self.target, self.source)
        pending = self._pending
        while pending and chain is not None:
            stamp_ns = pending[0]
            status, value = self.tree.evaluate(chain, stamp_ns)
            if status == WAIT:
                break
            del pending[0]
            if status == NEVER:
                self._drop('not evaluable', value)
                continue
            out.append((stamp_ns, value))
            self._last_ns = stamp_ns
        return out

    def finish(self):
        """Count the stamps still waiting (end of the recording) as dropped."""
        for _ in self._pending:
            self._drop('end of recording', 'transforms missing at the end of the recording')
        self._pending = []

    def _drop(self, reason, text):
        self.dropped[reason] += 1
        self.last_dropped = text

    def _check_generation(self):
        if self._generation != self.tree.generation:
            self._generation = self.tree.generation
            self._pending = []
            self._last_ns = None
