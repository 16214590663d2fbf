"""The fast CPU path, derived from each learner's own ``update``: recorded once, replayed.

A learner is written once, as plain torch (``bc.py``, ``awac.py``, ...): forwards,
``loss.backward()``, ``optimizer.step()``. On a CPU, the Python around the arithmetic
(autograd's engine, ``torch.optim``'s bookkeeping, per-op dispatch from Python) is a
large share of a chapter-size step (bench/RESULTS.md). So the training loop records one real step of the
learner's ``update`` as the exact list of operator calls it made (``make_fx`` in real
mode: the step runs for real while it is recorded, its backward and optimiser calls
included), and then replays that list for every later step: in C++
(``csrc/graph_runner.cpp``) where it is built, else as generated Python. The same
operators run on the same arguments, so replay gives the same bytes as running
``update`` itself (``tests/test_traced.py``), and an edit to a learner's loss is an
edit to what is replayed.

What a recordable ``update`` may not do: let a Python ``if`` or a number it reads
back from a tensor (``.item()``, ``float(t)``) depend on the data, or change a
hyper-parameter between steps; a recording that reads a tensor back is refused and
the learner runs eagerly instead, with a notice. Random draws are fine when they come
from a ``torch.Generator`` the learner owns: replay draws from it as the eager step
would.

The C++ replay runs the calls on ``TrainConfig.threads`` threads at once: the recording
also says which earlier calls each one must wait for (``_Hazards``), so the bytes are
the same with any number of threads.

``PUSHER_RL_STEP`` picks: ``auto`` (default: C++ replay where it builds, else Python
replay), ``cpp``, ``python``, or ``autograd`` (no recording: ``update`` every step).
"""

from __future__ import annotations

import operator
import os
import sys
from typing import Callable

import torch
from torch.fx.experimental.proxy_tensor import make_fx
from torch._guards import TracingContext, tracing
from torch._subclasses.fake_tensor import FakeTensorMode

from ..common.errors import UserError
from ..learners.data import Batch, MemberData
from ..learners.state import optimizers_of, walk

STEP_ENV = "PUSHER_RL_STEP"
STEP_MODES = ("auto", "cpp", "python", "autograd")
# Eager steps before the recording: optimisers create their state on first use, and a
# creation recorded would re-create it at every replay.
RECORD_AFTER_STEPS = 1
# Bookkeeping calls that change no tensor: the optimiser's profiler markers
_DROPPED = {"profiler._record_function_enter_new.default", "profiler._record_function_exit._RecordFunction",
            "profiler._record_function_enter.default", "profiler._record_function_exit.default"}

_notified: set[str] = set()


def notice(line: str) -> None:
    """Print ``line`` to stderr once per process (how the speed layer says it falls back)."""
    if line not in _notified:
        print(f"pusher-rl: {line}", file=sys.stderr, flush=True)
        _notified.add(line)


def step_mode() -> str:
    mode = os.environ.get(STEP_ENV, "auto").strip().lower() or "auto"
    if mode not in STEP_MODES:
        raise UserError(f"{STEP_ENV}={mode}: expected one of {', '.join(STEP_MODES)}")
    return mode


class NotRecordable(Exception):
    """The update did something a replay could not repeat faithfully."""


def record(fn: Callable[..., list[torch.Tensor]], inputs: list[torch.Tensor]):
    """Run ``fn(*inputs)`` once for real while recording its operator calls.

    Returns (graph module, the real outputs of this run). Raises ``NotRecordable`` part-way
    through when ``fn`` reads a tensor back into Python."""
    outputs: list[list[torch.Tensor]] = []

    def capture(*args):
        out = fn(*args)
        outputs.append(out)
        return out

    try:
        # one fake-tensor mode for the recorded values' metadata: without it make_fx
        # builds a mode (and captures a Python stack) for every value
        with tracing(TracingContext(FakeTensorMode(allow_fallback_kernels=True))), _RefuseReadBacks():
            gm = make_fx(capture, tracing_mode="real")(*inputs)
    except RuntimeError as exc:
        if "_local_scalar_dense" in str(exc) or "data-dependent" in str(exc):
            raise NotRecordable("the update reads a tensor back into Python (.item(), float(t) or a branch on one)") \
                from None
        raise
    graph = gm.graph
    for node in reversed(list(graph.nodes)):  # exits before their enters
        if node.op == "call_function" and str(node.target) in _DROPPED and not node.users:
            graph.erase_node(node)
    for node in list(graph.nodes):
        if node.op == "call_function" and node.target is torch.ops.aten.detach.default:
            node.replace_all_uses_with(node.args[0])
            graph.erase_node(node)
    _fold_constant_views(gm)
    for node in graph.nodes:  # the recording run's tensors (every activation): not needed to replay
        node.meta.clear()
    graph.lint()
    gm.recompile()
    return gm, [t.detach() for t in outputs[0]]


class _RefuseReadBacks(torch.overrides.TorchFunctionMode):
    """``.item()`` and ``float(t)`` go through an operator the recording sees and refuses;
    ``.numpy()`` and ``.tolist()`` read memory directly, so the recording would keep the
    value read once as a constant. Refuse those here instead."""

    _READS = {torch.Tensor.numpy, torch.Tensor.tolist, torch.Tensor.__array__}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func in self._READS:
            raise NotRecordable(f"the update reads a tensor back into Python (.{func.__name__}())")
        return func(*args, **(kwargs or {}))


# Operators that only make a view (new shape, strides or offset over the same memory)
_METADATA_VIEWS = {
    torch.ops.aten.select.int, torch.ops.aten.t.default, torch.ops.aten.transpose.int,
    torch.ops.aten.view.default, torch.ops.aten.unsqueeze.default, torch.ops.aten.squeeze.dim,
    torch.ops.aten.expand.default, torch.ops.aten.slice.Tensor, torch.ops.aten.permute.default,
}


def _fold_constant_views(gm) -> None:
    """Make each view of a constant (a member's slice of a stacked parameter, its
    transpose) once, here, instead of on every step: a view shares its parameter's
    memory, so it sees every in-place update of it, and replay reads the same bytes."""
    graph, n = gm.graph, 0
    for node in list(graph.nodes):
        if node.op != "call_function" or node.target not in _METADATA_VIEWS:
            continue
        base, *rest = node.args
        if not (isinstance(base, torch.fx.Node) and base.op == "get_attr") or any(
                isinstance(a, torch.fx.Node) for a in rest) or node.kwargs:
            continue
        with torch.no_grad():
            view = node.target(getattr(gm, base.target).detach(), *rest)
        name = f"_constant_view{n}"
        n += 1
        gm.register_buffer(name, view, persistent=False)
        with graph.inserting_before(node):
            folded = graph.get_attr(name)
        node.replace_all_uses_with(folded)
        graph.erase_node(node)


class PythonReplay:
    """The recording as generated Python (one torch op call per recorded call)."""

    def __init__(self, gm):
        self.gm = gm

    def __call__(self, inputs: list[torch.Tensor]) -> list[torch.Tensor]:
        with torch.inference_mode():
            return self.gm(*inputs)


class CppReplay:
    """The recording replayed by ``csrc/graph_runner.cpp``."""

    def __init__(self, gm, extension, workers: int = 1, choose: bool = False):
        self.program = _to_program(gm, extension, workers, choose)
        self.noticed = False

    def __call__(self, inputs: list[torch.Tensor]) -> list[torch.Tensor]:
        out = self.program.run(inputs)
        if not self.noticed and self.program.measured:
            self.noticed = True
            if self.program.why_in_order:
                notice(f"training steps run on one thread: {self.program.why_in_order}")
        return out

    @property
    def threads(self) -> int:
        """Threads the steps run on (before the calls are timed: the ones they will use)."""
        if not self.program.measured:
            return self.program.workers
        return self.program.threads_in_use

    def set_threads(self, workers: int, choose: bool) -> None:
        self.program.set_workers(workers, choose)


def _to_program(gm, extension, workers: int = 1, choose: bool = False):
    """Translate the recorded graph into the C++ Program's calls and value slots, with
    what each call waits for when ``workers`` threads replay it (``choose``: at most
    that many, as many as the timed replay says pay)."""
    nodes = list(gm.graph.nodes)
    slots: dict = {}  # node -> slot, or list of slots for several returns
    count = 0

    def new_slot() -> int:
        nonlocal count
        count += 1
        return count - 1

    inputs, outputs, constants, keep = [], [], {}, set()
    calls = []  # ("call", op, specs, out_slots, reads) | ("elem", src, index, out, reads)
    hazards = _Hazards()
    for node in nodes:
        if node.op == "placeholder":
            slots[node] = new_slot()
            inputs.append(slots[node])
            keep.add(slots[node])
        elif node.op == "get_attr":
            slots[node] = new_slot()
            constants[slots[node]] = getattr(gm, node.target)
            keep.add(slots[node])
            hazards.constant(slots[node], constants[slots[node]])
        elif node.op == "output":
            outputs = [slots[n] for n in node.args[0]]
            keep.update(outputs)
        elif node.target is operator.getitem:
            source, index = node.args
            if isinstance(slots[source], list):  # one slot per return: an alias
                slots[node] = slots[source][index]
            else:
                slots[node] = new_slot()
                hazards.call(len(calls), reads=[slots[source]], writes=[], aliases=[(slots[node], [slots[source]])],
                             outputs=[slots[node]])
                calls.append(("elem", slots[source], index, slots[node], [slots[source]]))
        else:
            op = node.target
            schema = op._schema
            specs, reads = [], []
            arg_slots: list[list[int]] = []  # per schema argument, the slots it reads
            for i, arg in enumerate(schema.arguments):
                if i < len(node.args):
                    value = node.args[i]
                elif arg.name in node.kwargs:
                    value = node.kwargs[arg.name]
                elif arg.has_default_value():
                    value = arg.default_value
                else:
                    raise NotRecordable(f"{op}: no value for argument {arg.name}")
                if isinstance(value, torch.fx.Node):
                    specs.append(("slot", slots[value]))
                    arg_slots.append([slots[value]])
                elif isinstance(value, (list, tuple)) and any(isinstance(v, torch.fx.Node) for v in value):
                    ids = [-1 if v is None else slots[v] for v in value]
                    specs.append(("slots", ids))
                    arg_slots.append([s for s in ids if s >= 0])
                elif isinstance(value, (bool, int, float)) and isinstance(arg.type, torch.TensorType):
                    specs.append(("wrapped", value))  # a Python number where a Tensor goes
                    arg_slots.append([])
                else:
                    specs.append(("const", value))
                    arg_slots.append([])
                reads.extend(arg_slots[-1])
            n_out = len(schema.returns)
            out = [new_slot() for _ in range(n_out)]
            slots[node] = out if n_out > 1 else (out[0] if out else None)
            hazards.op_call(len(calls), op, arg_slots, out)
            calls.append(("call", op, specs, out, reads))

    # release each slot after its last read (or at once if never read), except
    # inputs, constants and outputs
    last_read: dict[int, int] = {}
    for i, call in enumerate(calls):
        for s in call[-1]:
            last_read[s] = i
    program = extension.Program(count)
    for slot, tensor in constants.items():
        program.set_constant(slot, tensor)
    program.set_inputs(inputs)
    program.set_outputs(outputs)
    for i, call in enumerate(calls):
        produced = call[3] if call[0] == "call" else [call[3]]
        release = [s for s in call[-1] if last_read[s] == i and s not in keep]
        release += [s for s in produced if s not in last_read and s not in keep]
        if call[0] == "call":
            op = call[1]
            name, _, overload = op.name().partition(".")
            program.add_call(name, overload, call[2], call[3], release)
        else:
            program.add_list_element(call[1], call[2], call[3], release)
    program.set_dependencies(hazards.waits_for, sorted(keep), hazards.groups(count))
    program.set_workers(workers, choose)
    return program


# ATen operators that return a view of their first argument without an alias annotation
_UNDECLARED_VIEWS = {"aten::_unsafe_view", "aten::_reshape_alias"}


class _Hazards:
    """Which earlier calls each recorded call must wait for, so that calls can run on
    several threads and still each see exactly the tensors it saw in the recording.

    Tensors are grouped by what they may share memory with, as the operator schemas
    declare it (a view with its base, an in-place result with its input) and constants
    by their storage: a group's writer waits for the earlier writer and every reader
    since, a reader for the last writer. Random draws all touch one generator group, so
    they happen in the recorded order."""

    RNG = -1

    def __init__(self):
        self.parent: dict[int, int] = {}
        self.last_writer: dict[int, int] = {}
        self.readers: dict[int, set[int]] = {}
        self.by_storage: dict[int, int] = {}
        self.producer: dict[int, int] = {}  # slot -> the call that filled it
        self.waits_for: list[list[int]] = []

    def root(self, slot: int) -> int:
        self.parent.setdefault(slot, slot)
        while self.parent[slot] != slot:
            self.parent[slot] = self.parent[self.parent[slot]]
            slot = self.parent[slot]
        return slot

    def _union(self, a: int, b: int) -> None:
        ra, rb = self.root(a), self.root(b)
        if ra == rb:
            return
        self.parent[rb] = ra  # both histories now belong to ra
        writers = [w for w in (self.last_writer.pop(ra, None), self.last_writer.pop(rb, None)) if w is not None]
        if writers:
            self.last_writer[ra] = max(writers)
        self.readers[ra] = self.readers.pop(ra, set()) | self.readers.pop(rb, set())

    def constant(self, slot: int, value) -> None:
        """Constants (parameters, optimiser state) that share a storage are one group."""
        if isinstance(value, torch.Tensor):
            ptr = value.untyped_storage().data_ptr()
            if ptr in self.by_storage:
                self._union(self.by_storage[ptr], slot)
            elif ptr:
                self.by_storage[ptr] = slot

    def groups(self, n_slots: int) -> list[int]:
        """Each slot's group (the C++ replay checks them against the memory the values
        really share, and runs on one thread if an operator shares memory it does not
        declare)."""
        return [self.root(s) if s in self.parent else s for s in range(n_slots)]

    def op_call(self, index: int, op, arg_slots: list[list[int]], out_slots: list[int]) -> None:
        schema = op._schema
        writes, aliases = [], []
        for arg, used in zip(schema.arguments, arg_slots):
            if arg.alias_info is not None and arg.alias_info.is_write:
                writes.extend(used)
        if schema.name in _UNDECLARED_VIEWS and out_slots:  # views whose schemas do not say so
            aliases.append((out_slots[0], list(arg_slots[0])))
        for ret, slot in zip(schema.returns, out_slots):
            if ret.alias_info is None:
                continue
            sets = set(ret.alias_info.before_set)
            same = [s for arg, used in zip(schema.arguments, arg_slots) if arg.alias_info is not None
                    and (not sets or sets & set(arg.alias_info.before_set)) for s in used]
            aliases.append((slot, same))
        if torch.Tag.nondeterministic_seeded in op.tags:
            writes.append(self.RNG)
        self.call(index, reads=[s for used in arg_slots for s in used], writes=writes, aliases=aliases,
                  outputs=out_slots)

    def call(self, index: int, reads: list[int], writes: list[int], aliases: list[tuple[int, list[int]]],
             outputs: list[int]) -> None:
        read_roots = {self.root(s) for s in reads}
        write_roots = {self.root(s) for s in writes}
        waits = {self.producer[s] for s in reads if s in self.producer}
        for r in read_roots | write_roots:
            if r in self.last_writer:
                waits.add(self.last_writer[r])
        for r in write_roots:
            waits |= self.readers.get(r, set())
        for r in read_roots - write_roots:
            self.readers.setdefault(r, set()).add(index)
        for r in write_roots:
            self.last_writer[r] = index
            self.readers[r] = set()
        for out in outputs:
            self.producer[out] = index
        for out, sources in aliases:
            for s in sources:
                self._union(s, out)
        waits.discard(index)
        self.waits_for.append(sorted(waits))


class RecordedStep:
    """``update(data.gather(idx))``: eager for ``RECORD_AFTER_STEPS``, recorded on the next
    step, replayed after that. The batch gather is part of the recording, so a step's
    only input is its (members, batch) index tensor."""

    def __init__(self, update: Callable[[Batch], dict], data: MemberData, mode: str, workers: int = 1,
                 choose_workers: bool = False):
        self.update, self.data, self.mode = update, data, mode
        self.workers, self.choose_workers = workers, choose_workers
        self._python_threads: int | None = None  # torch's threads under the Python replay
        self.keys: list[str] | None = None
        self.replay: Callable | None = None
        self.eager_steps = 0
        self.kind = "eager"

    def __call__(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        if self.replay is not None:
            return dict(zip(self.keys, self.replay([idx])))
        if self.eager_steps < RECORD_AFTER_STEPS or self.kind == "not recordable":
            self.eager_steps += 1
            return self.update(self.data.gather(idx))
        return self._record(idx)

    @property
    def threads(self) -> int:
        """Threads the replayed steps run on."""
        if isinstance(self.replay, CppReplay):
            return self.replay.threads
        return self._python_threads or self.workers

    def offer_threads(self, n: int) -> None:
        """Let the following steps use up to ``n`` threads (as many as pay), e.g. when
        cores another run had are free; the bytes trained do not change. Only the C++
        replay spreads a step over threads; the other paths keep theirs."""
        n = max(1, int(n))
        if n == self.workers:
            return
        self.workers, self.choose_workers = n, n > 1
        if isinstance(self.replay, CppReplay):
            self.replay.set_threads(n, n > 1)

    def _record(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        def step(index):
            losses = self.update(self.data.gather(index))
            if self.keys is None:
                self.keys = sorted(losses)
            return [losses[k] for k in self.keys]

        snapshot = Snapshot(getattr(self.update, "__self__", None))
        try:
            gm, outputs = record(step, [idx])  # this step, taken for real
        except Exception as exc:  # noqa: BLE001 - stopped part-way: undo what it did, take it eagerly
            # (an error of the update itself is raised again there, as without recording)
            snapshot.restore()
            self._refuse(str(exc) if isinstance(exc, NotRecordable) else
                         f"its update could not be recorded ({type(exc).__name__}: {str(exc).splitlines()[0][:160]})")
            self.keys = None
            return self.update(self.data.gather(idx))
        try:
            self.replay, self.kind = self._replayer(gm)
        except NotRecordable as exc:
            self._refuse(str(exc))
        _free_grads(self.update)
        return dict(zip(self.keys, outputs))

    def _refuse(self, why: str) -> None:
        notice(f"training runs {type(getattr(self.update, '__self__', None)).__name__} eagerly: {why}")
        self.kind = "not recordable"

    def _replayer(self, gm):
        if self.mode in ("auto", "cpp"):
            from . import graph_runner

            reason = graph_runner.unavailable_reason()
            if reason is None:
                return CppReplay(gm, graph_runner.extension(), self.workers, self.choose_workers), "cpp"
            if self.mode == "cpp":
                raise UserError(f"{STEP_ENV}=cpp: the C++ step replayer cannot be built here: {reason}")
            notice(f"the C++ step replayer is not available ({reason}); replaying steps in Python")
        self._python_threads = torch.get_num_threads()  # one Python thread issues the calls, each on torch's
        return PythonReplay(gm), "python"


class Snapshot:
    """Copies of every tensor and generator state a learner's step can change (its
    modules' parameters and buffers, its loose parameters, its optimisers' parameters
    and state, its generators), to undo a recording that stopped part-way."""

    def __init__(self, learner):
        self.tensors: list[tuple[torch.Tensor, torch.Tensor]] = []
        self.generators: list[tuple[torch.Generator, torch.Tensor]] = []
        seen: set[int] = set()
        for _, obj in walk(learner, depth=2):
            if isinstance(obj, torch.nn.Module):
                for t in [*obj.parameters(), *obj.buffers()]:
                    self._keep(t, seen)
            elif isinstance(obj, torch.Tensor):  # a loose parameter (SAC's log-std)
                self._keep(obj, seen)
            elif isinstance(obj, torch.optim.Optimizer):
                for group in obj.param_groups:
                    for t in group["params"]:
                        self._keep(t, seen)
                for state in obj.state.values():
                    for t in state.values():
                        if isinstance(t, torch.Tensor):
                            self._keep(t, seen)
            elif isinstance(obj, torch.Generator):
                self.generators.append((obj, obj.get_state()))

    def _keep(self, t: torch.Tensor, seen: set[int]) -> None:
        if id(t) not in seen:
            seen.add(id(t))
            self.tensors.append((t, t.detach().clone()))

    def restore(self) -> None:
        with torch.no_grad():
            for t, copy in self.tensors:
                t.copy_(copy)
        for gen, state in self.generators:
            gen.set_state(state)


def _free_grads(update) -> None:
    """The recording leaves the parameters' ``.grad`` set; replay never reads them."""
    learner = getattr(update, "__self__", None)
    for opt in optimizers_of(learner):
        for group in opt.param_groups:
            for p in group["params"]:
                p.grad = None

