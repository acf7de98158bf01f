"""A CUDA device emulated on a CPU-only torch, for the tests: device mixing that CUDA would refuse raises here too.

No GPU is lent to CI, and the bugs a GPU found (2026-12-04, docs/benchmarks.md section 9) were all a CPU tensor meeting
a CUDA one after a fit. Under :func:`install` (a ``TorchFunctionMode``) every tensor counts as "CUDA" unless it was
made on the CPU: a factory call without ``device=``, ``.cpu()`` / ``.to("cpu")``, ``torch.from_numpy``, or an op whose
tensor inputs are all CPU. ``device="cuda"`` and ``.to("cuda")`` are redirected to the CPU and tag the result CUDA;
``t.device`` answers ``cuda:0``. Raised as CUDA would: an op mixing a CUDA tensor with a CPU tensor of dim >= 1 (0-dim
CPU tensors and CPU indices into a CUDA tensor are allowed), a CPU tensor indexed by a CUDA index or mask, an
index_put of CPU values into a CUDA tensor, ``.numpy()`` of a CUDA tensor. Install it in a fresh process only
(it patches ``torch.cuda`` for the process). Written by hand: no library emulates a device's placement rules.
"""
import json
import os
import traceback

import torch
from torch.overrides import TorchFunctionMode, resolve_name
from torch.utils._pytree import tree_flatten, tree_map

CUDA = torch.device("cuda", 0)
CPU = torch.device("cpu")
LOG = os.environ.get("FAKECUDA_LOG")  # a JSON-lines log of each distinct violation, where set
RAISE = os.environ.get("FAKECUDA_RAISE", "1") == "1"
_seen = set()

def is_cpu(t):
    return getattr(t, "_fc_cpu", False)

def tag(t, cpu):
    try:
        t._fc_cpu = bool(cpu)
    except Exception:
        pass
    return t

def _dev(v):
    if v is None:
        return None
    if isinstance(v, torch.Tensor):
        return CPU if is_cpu(v) else CUDA
    if isinstance(v, (str, torch.device)):
        d = torch.device(v)
        return CUDA if d.type == "cuda" else CPU
    if isinstance(v, int) and not isinstance(v, bool):
        return CUDA
    return None

def report(kind, msg):
    stack = traceback.extract_stack()[:-2]
    frames = [f for f in stack if "/skyfit/" in f.filename or "/tests/" in f.filename]
    where = frames[-1] if frames else stack[-1]
    key = (kind, where.filename, where.lineno)
    rec = {"kind": kind, "msg": msg, "file": where.filename, "line": where.lineno, "code": where.line,
           "stack": [f"{f.filename.split('/work/main/')[-1]}:{f.lineno} {f.line}" for f in frames[-8:]]}
    if key not in _seen and LOG:
        _seen.add(key)
        with open(LOG, "a") as fh:
            fh.write(json.dumps(rec) + "\n")
    if RAISE:
        raise RuntimeError(f"[fakecuda] {kind}: {msg} at {where.filename}:{where.lineno}")

MOVES = {"torch.Tensor.to", "torch.Tensor.cpu", "torch.Tensor.cuda", "torch.Tensor.copy_", "torch.Tensor.new_tensor",
         "torch.Tensor.type_as", "torch.Tensor.__setitem__"}

class FakeCuda(TorchFunctionMode):
    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        name = resolve_name(func) or getattr(func, "__name__", repr(func))
        if name == "torch.Tensor.device.__get__":
            return CPU if is_cpu(args[0]) else CUDA
        if name == "torch.Tensor.is_cuda.__get__":
            return not is_cpu(args[0])
        if name == "torch.Tensor.get_device":
            return -1 if is_cpu(args[0]) else 0
        if name in ("torch.Tensor.numpy", "torch.Tensor.__array__"):
            if not is_cpu(args[0]):
                report("numpy_on_cuda", f"{name} of a CUDA tensor {tuple(args[0].shape)}")
            return func(*args, **kwargs)
        if name == "torch.Tensor.grad.__get__":
            g = func(*args, **kwargs)
            if g is not None:
                tag(g, is_cpu(args[0]))
            return g
        # target device of the call
        target = None
        if "device" in kwargs:
            target = _dev(kwargs["device"])
            if target is not None:
                kwargs["device"] = "cpu"
        if name == "torch.Tensor.to":
            a = list(args)
            for i in range(1, len(a)):
                d = _dev(a[i]) if not isinstance(a[i], torch.dtype) else None
                if d is not None:
                    target = d
                    if isinstance(a[i], torch.Tensor):
                        a[i] = a[i].dtype  # keep the dtype, drop the device
                    else:
                        a[i] = "cpu"
            if "other" in kwargs:
                target = _dev(kwargs["other"]); kwargs["dtype"] = kwargs.pop("other").dtype
            args = tuple(a)
        elif name == "torch.Tensor.cpu":
            target = CPU
        elif name == "torch.Tensor.cuda":
            target = CUDA
            args = args[:1]; kwargs = {}
            func = torch.Tensor.clone
        flat, _ = tree_flatten((args, kwargs))
        tens = [t for t in flat if isinstance(t, torch.Tensor)]
        cu = [t for t in tens if not is_cpu(t)]
        cp = [t for t in tens if is_cpu(t) and t.ndim >= 1]
        if cu and cp and name not in MOVES and target is None:
            ok = False
            if name == "torch.Tensor.__getitem__":
                ok = not is_cpu(args[0])  # CPU indices into a CUDA tensor are allowed
                if is_cpu(args[0]):
                    report("cpu_indexed_by_cuda", f"CPU tensor {tuple(args[0].shape)} indexed by a CUDA index")
            if not ok:
                shapes = [("cuda", tuple(t.shape)) for t in cu[:3]] + [("cpu", tuple(t.shape)) for t in cp[:3]]
                report("mixed", f"{name} with {shapes}")
        if name == "torch.Tensor.__setitem__" and tens:
            selfc = not is_cpu(args[0])
            idx = args[1]; val = args[2] if len(args) > 2 else None
            idx_t = [t for t in tree_flatten(idx)[0] if isinstance(t, torch.Tensor)]
            if not selfc and any(not is_cpu(t) for t in idx_t):
                report("cpu_indexed_by_cuda", "CPU tensor written at a CUDA index")
            if selfc and idx_t and isinstance(val, torch.Tensor) and is_cpu(val) and val.ndim >= 1:
                report("index_put_cpu_values", f"CUDA tensor index_put with CPU values {tuple(val.shape)}")
            if not selfc and isinstance(val, torch.Tensor) and not is_cpu(val) and val.ndim >= 1 and idx_t:
                report("index_put_cuda_values", "CPU tensor index_put with CUDA values")
        out = func(*args, **kwargs)
        # output tag
        if target is not None:
            out_cpu = target == CPU
        elif tens:
            out_cpu = all(is_cpu(t) for t in tens)
        else:
            out_cpu = True  # a factory without a device: the default device
        if name in ("torch.Tensor.__setitem__",) or out is None:
            return out
        def fix(t):
            if isinstance(t, torch.Tensor):
                if any(t is s for s in tens) and is_cpu(t) != out_cpu and name in ("torch.Tensor.to", "torch.Tensor.cpu"):
                    t = t.clone()  # a device move makes a new tensor
                if not any(t is s for s in tens):
                    tag(t, out_cpu)
                elif name in ("torch.Tensor.to", "torch.Tensor.cpu", "torch.Tensor.cuda"):
                    tag(t, out_cpu)
            return t
        return tree_map(fix, out)

def install():
    torch.cuda.is_available = lambda: True
    torch.cuda.device_count = lambda: 1
    torch.cuda.mem_get_info = lambda *a, **k: (100 * 2**30, 140 * 2**30)
    torch.cuda.synchronize = lambda *a, **k: None
    torch.cuda.get_device_name = lambda *a, **k: "FakeCUDA"
    for nm in ("from_numpy", "frombuffer", "from_dlpack"):
        f = getattr(torch, nm, None)
        if f is not None:
            def w(*a, _f=f, **k):
                return tag(_f(*a, **k), True)
            setattr(torch, nm, w)
    m = FakeCuda()
    m.__enter__()
    return m
