"""Real-time inference (issue #51): a network as an ONNX Runtime session on one thread, the deployment
stack's graph optimisation (and int8 dynamic quantisation where it keeps accuracy), and the estimator the
closed loop calls per frame.

:func:`ort_session` exports a network in memory (the legacy TorchScript exporter, as ``export --onnx``) and
opens it with every graph optimisation, ``intra_op_num_threads = 1`` and sequential execution: one core, batch
1, no thread hand-off.  ``output = "commands"`` exports only the modal network's commands (what a mirror
takes: no phase map); ``"phase"`` the phase on the crop (what evaluation measures).  ``quantize = "int8"``:
weights int8, activations quantised per call (ONNX Runtime's dynamic quantisation of the matrix products and
convolutions).  :class:`RealtimeEstimator` is the loop's estimator: ``estimate({"psf": (B, 8, S, S)}) ->
(B, A, A)`` through the session."""

from __future__ import annotations

import io
import tempfile
import warnings
from pathlib import Path

import numpy as np

from ..validation import ValidationError

__all__ = ["ort_session", "RealtimeEstimator", "OUTPUTS", "QUANTIZE"]

OUTPUTS = ("phase", "commands")
QUANTIZE = (None, "int8")


def _onnx_bytes(model, output: str, opset: int = 17) -> bytes:
    import torch

    class _Commands(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, x):
            return self.net.commands(x)

    if output not in OUTPUTS:
        raise ValidationError(f"output: expected one of {', '.join(OUTPUTS)}, got {output!r}")
    if output == "commands" and not hasattr(model, "commands"):
        raise ValidationError("output: commands needs a modal network (model.kind = \"modal\")")
    net = _Commands(model) if output == "commands" else model
    s = model.config.input_size
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net.eval(), (torch.rand(1, 8, s, s),), buf, input_names=["psf"], output_names=[output],
                          dynamic_axes={"psf": {0: "batch"}, output: {0: "batch"}}, opset_version=opset, dynamo=False)
    return buf.getvalue()


def ort_session(model, output: str = "phase", quantize: str | None = None, threads: int = 1):
    """An ONNX Runtime session of ``model`` (input ``psf`` (B, 8, S, S) float32; output ``output``) on
    ``threads`` intra-op threads, sequential, every graph optimisation; ``quantize = "int8"``: dynamic int8."""
    import onnxruntime as ort

    if quantize not in QUANTIZE:
        raise ValidationError(f"quantize: expected none or int8, got {quantize!r}")
    data = _onnx_bytes(model, output)
    if quantize == "int8":
        from onnxruntime.quantization import QuantType, quantize_dynamic

        with tempfile.TemporaryDirectory() as d:
            src, dst = Path(d) / "fp32.onnx", Path(d) / "int8.onnx"
            src.write_bytes(data)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                quantize_dynamic(str(src), str(dst), weight_type=QuantType.QInt8)
            data = dst.read_bytes()
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(data, so, providers=["CPUExecutionProvider"])


class RealtimeEstimator:
    """A network's phase estimate through an ONNX Runtime session on one thread (what a real-time loop would
    run); torch when onnxruntime is absent.  ``estimate({"psf": (B, 8, S, S)}) -> (B, A, A)`` rad.  The
    session is made on first use and never pickled (a worker process makes its own)."""

    name = "realtime"

    def __init__(self, model, quantize: str | None = None, threads: int = 1):
        if quantize not in QUANTIZE:
            raise ValidationError(f"quantize: expected none or int8, got {quantize!r}")
        self.model, self.quantize, self.threads = model, quantize, int(threads)
        self._session = None

    def __getstate__(self) -> dict:
        return {"model": self.model, "quantize": self.quantize, "threads": self.threads}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, _session=None)

    @property
    def session(self):
        if self._session is None:
            try:
                self._session = ort_session(self.model, "phase", self.quantize, self.threads)
            except ImportError:
                self._session = False
        return self._session

    def estimate(self, batch: dict) -> np.ndarray:
        x = np.ascontiguousarray(batch["psf"], np.float32)
        if self.session:
            return self.session.run(None, {"psf": x})[0]
        import torch

        with torch.inference_mode():
            return self.model(torch.from_numpy(x)).numpy()
