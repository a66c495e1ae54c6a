"""Training steps replayed as CUDA graphs: the proposal sampler's step has fixed shapes (its batch
and its samples per ray never change), so its hundreds of kernel launches can be captured once and
replayed, without the host work that otherwise leaves the GPU idle between them.

A step comes in two kinds (the proposal networks learn at it or not), one graph each. The first
step of a kind runs eagerly on the capture stream (a real step, which also makes the lazily made
state the capture needs: optimizer moments, cuBLAS workspaces, the guard's flags), then that kind
is captured; its later steps replay the graph. What a replay touches keeps its memory across
replays: parameters, optimizer state, the random generator (registered with each graph, so every
replay draws new rays and samples), the gradients and the outputs (one set per graph, each in its
own memory pool). Anything the host must change between replays lives in a device tensor that the
caller updates before :meth:`GraphedSteps.__call__` (the learning rate, the step counter).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch


class GraphedSteps:
    """``body(kind) -> {name: device scalar}`` is one training step of ``kind`` (a hashable
    value), from its random batch to its optimizer step, with no host synchronisation and no
    shape that changes between steps of a kind. ``params``: the parameters whose gradients
    ``body`` makes; ``generator``: the CUDA generator its random draws use."""

    def __init__(self, body: Callable[[object], dict[str, torch.Tensor]], params: Sequence[torch.Tensor],
                 generator: torch.Generator) -> None:
        if generator.device.type != "cuda":
            raise ValueError(f"CUDA graphs need a CUDA generator, got one on {generator.device}")
        self.body, self.params, self.generator = body, list(params), generator
        self.stream = torch.cuda.Stream(generator.device)
        self._graphs: dict[object, torch.cuda.CUDAGraph] = {}
        self._outputs: dict[object, dict[str, torch.Tensor]] = {}
        self._grads: dict[object, list[torch.Tensor | None]] = {}

    @property
    def captured(self) -> tuple[object, ...]:
        """The kinds captured so far."""
        return tuple(self._graphs)

    def __call__(self, kind: object) -> dict[str, torch.Tensor]:
        """Run one step of ``kind``; its outputs stay valid until the next step of that kind.
        After the call each parameter's ``.grad`` is this step's gradient."""
        graph = self._graphs.get(kind)
        if graph is None:
            return self._run_then_capture(kind)
        graph.replay()
        for p, g in zip(self.params, self._grads[kind], strict=True):
            p.grad = g
        return self._outputs[kind]

    def _run_then_capture(self, kind: object) -> dict[str, torch.Tensor]:
        main = torch.cuda.current_stream(self.stream.device)
        self.stream.wait_stream(main)
        with torch.cuda.stream(self.stream):
            ran = self.body(kind)
        main.wait_stream(self.stream)
        ran = {name: value.clone() for name, value in ran.items()}  # on the main stream, after the step
        grads = [p.grad for p in self.params]
        # Gradients set to None before the capture: the graph's backward then writes them into its
        # own pool (assigning, not accumulating into another graph's gradients).
        for p in self.params:
            p.grad = None
        graph = torch.cuda.CUDAGraph()
        graph.register_generator_state(self.generator)
        with torch.cuda.graph(graph, stream=self.stream):
            self._outputs[kind] = self.body(kind)
        self._grads[kind] = [p.grad for p in self.params]
        self._graphs[kind] = graph
        for p, g in zip(self.params, grads, strict=True):  # the step that ran, until the next one
            p.grad = g
        return ran
