"""
The matching costs: one `CostSpec` each, in the registry `COSTS`.

A spec says all the pipeline, the backends, the memory model, the node's parameters and the
evaluation need to know of a cost; none of them names a cost. Adding one is a kernel (CPU,
and CUDA if it runs on a GPU) and a `register(CostSpec(...))` before the pipeline or the
node is made (doc/api.md, "Adding a matching cost").
"""
from dataclasses import dataclass, field
import importlib
from typing import Any, Callable

# Kernels are given as 'module:function' (imported on first use, so that the registry needs
# neither numba-cuda nor the kernels' compilation) or as the function itself.
Kernel = Callable[..., None] | str


@dataclass(frozen=True)
class CostSpec:
    """
    One matching cost: its values, windows and kernels.

    Attributes
    ----------
    name : str
        The cost's name: ``cost`` in StereoConfig, the node's parameter group
        (``<name>.P1``, ...) and the evaluation's methods (``<name>``, ``<name>+gcp``).
    summary : str
        What the cost is, in a few words, for the node's ``cost`` parameter.
    windows : tuple of int
        (low, high): the odd window sides it takes, px, both ends included.
    top : Callable[[int], float]
        The largest cost of a window side, in cost units: what invalid cells get.
    standardized : bool
        Its kernels read each image standardized (`images.standardize`), else gray.
    integer : bool
        Its costs are integers: with integer-scalable P1, P2, C_hi, C_low the pipeline keeps
        its volumes in uint16 fixed point (`memory.fixed_point_scale`).
    cpu : Kernel
        ``f(left, right, max_disp, window, scale, invalid, out, cancel)``: writes
        scale * cost, at most `invalid`, into the float32 or uint16 volume `out`
        (H, W, max_disp) from float32 images (H, W), `invalid` into cells whose windows
        leave an image; `cancel` is a `cancel.flag_array`.
    cuda : Kernel or None
        ``f(images, window, scale, invalid, out)``: the same into a tensor on a GPU,
        `images` a float32 tensor (2, H, W); None: the cost runs on the CPU only.
    presets : dict
        The cost's values of each preset it has ('default' required, the others over
        it), by StereoConfig field: p1, p2, theta, c_hi, c_low, gcp_lr_check,
        gcp_plain_check, plain_check.

    """

    name: str
    summary: str
    windows: tuple[int, int]
    top: Callable[[int], float]
    standardized: bool
    integer: bool
    cpu: Kernel
    cuda: Kernel | None
    presets: dict[str, dict[str, Any]] = field(default_factory=dict)

    def kernel(self, device: str) -> Callable[..., None]:
        """Return the kernel for 'cpu' or 'cuda'; ValueError if the cost has none there."""
        found = self.cpu if device == 'cpu' else self.cuda
        if found is None:
            raise ValueError(f'cost {self.name!r} has no CUDA kernel: use device cpu')
        if isinstance(found, str):
            module, name = found.split(':')
            found = getattr(importlib.import_module(module), name)
        return found


COSTS: dict[str, CostSpec] = {}


def register(spec: CostSpec) -> CostSpec:
    """Add `spec` to COSTS and return it; ValueError if its name is taken or it is unusable."""
    low, high = spec.windows
    if spec.name in COSTS:
        raise ValueError(f'a cost named {spec.name!r} is registered already')
    if not (spec.name.isidentifier() and '+' not in spec.name):
        raise ValueError(f'a cost name must be an identifier, got {spec.name!r}')
    if not (low % 2 == 1 and high % 2 == 1 and 1 <= low <= high):
        raise ValueError(f'windows must be odd sides low <= high, got {spec.windows}')
    if 'default' not in spec.presets:
        raise ValueError(f'cost {spec.name!r} has no default preset values')
    COSTS[spec.name] = spec
    return spec


def cost_spec(name: str) -> CostSpec:
    """Return the spec of the cost `name`; ValueError naming the registered ones if none."""
    if name not in COSTS:
        raise ValueError(f'cost must be one of {tuple(COSTS)}, got {name!r}')
    return COSTS[name]


SAD_MAX = 3.2  # SAD's truncation, in image standard deviations (the paper's range)
register(CostSpec(
    name='census',
    summary='Hamming distance of Census bit strings',
    windows=(3, 11),  # its bits fit two uint64 words
    top=lambda window: float(window * window - 1),
    standardized=False,
    integer=True,
    cpu='gcp_stereo_ros.stereo.cost:census_volume',
    cuda='gcp_stereo_ros.stereo.cuda.cost:census_volume',
    presets={
        # Chosen by cross-validation on the validation frames (doc/method.md); theta on the
        # calibrated scale (cnn.network.calibrated).
        'default': {'p1': 12.0, 'p2': 128.0, 'theta': 0.2, 'c_hi': 200.0, 'c_low': 2.0,
                    'gcp_lr_check': True, 'gcp_plain_check': True, 'plain_check': 1.5},
        # The paper's (Zhong et al., section 4); its theta read on our calibrated scale.
        'paper': {'p1': 4.0, 'p2': 128.0, 'theta': 0.60, 'c_hi': 200.0, 'c_low': 1.3,
                  'gcp_lr_check': False, 'gcp_plain_check': False},
        # The defaults': plain SGM's second opinion is worth its time at half resolution
        # too (doc/speed.md, "The real-time preset").
        'realtime': {},
    }))
register(CostSpec(
    name='sad',
    summary='mean absolute difference of standardized intensities',
    windows=(3, 31),
    top=lambda window: SAD_MAX,
    standardized=True,
    integer=False,
    cpu='gcp_stereo_ros.stereo.cost:sad_volume',
    cuda='gcp_stereo_ros.stereo.cuda.cost:sad_volume',
    presets={
        # plain_check and gcp_plain_check off: plain SGM on SAD costs is wrong across the
        # textureless Middlebury scenes (doc/published.md, doc/method.md).
        'default': {'p1': 0.02, 'p2': 0.5, 'theta': 0.2, 'c_hi': 5.0, 'c_low': 0.001,
                    'gcp_lr_check': True, 'gcp_plain_check': False, 'plain_check': 0.0},
        'paper': {'p1': 1.0, 'p2': 14.0, 'theta': 0.55, 'c_hi': 5.0, 'c_low': 0.001,
                  'gcp_lr_check': False, 'gcp_plain_check': False},
    }))
