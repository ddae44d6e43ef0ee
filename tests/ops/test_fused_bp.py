r"""The fused Triton kernel against a plain loop reference: on CUDA where
available, else in Triton's CPU interpreter (if Triton is installed)."""
import math
import os
import subprocess
import sys

import pytest
import torch

triton = pytest.importorskip('triton')

SCRIPT = r'''
import math, sys, torch
from tg_nebp.models import GaussianRange
from tg_nebp.ops.fused_bp import fused_bp_segment_sum
device = sys.argv[1]
g = torch.Generator().manual_seed(0)
num_nodes, num_particles, num_edges = 9, 45, 30
pos_x = 5 * torch.randn(num_nodes, num_particles, generator=g)
pos_y = 5 * torch.randn(num_nodes, num_particles, generator=g)
log_w = torch.randn(num_nodes, num_particles, generator=g)
src = torch.randint(0, num_nodes, (num_edges,), generator=g)
dst = torch.randint(0, num_nodes, (num_edges,), generator=g)
dst, perm = dst.sort()
src = src[perm]
ranges = 6 * torch.rand(num_edges, 1, generator=g)
ptr = torch.zeros(num_nodes + 1, dtype=torch.long)
ptr[1:] = torch.bincount(dst, minlength=num_nodes).cumsum(0)
sigma = 0.7
args = [t.to(device) for t in (pos_x, pos_y, log_w, ranges, src, ptr)]
model = GaussianRange(sigma)
out = fused_bp_segment_sum(*args, model.fused_log_pdf, model.fused_constants(),
                           block=16).cpu()
worst = 0.0
for i in range(num_nodes):
    for k in range(num_particles):
        total = 0.0
        for e in range(num_edges):
            if int(dst[e]) != i:
                continue
            j = int(src[e])
            d = math.hypot(float(pos_x[j, k] - pos_x[i, k]),
                           float(pos_y[j, k] - pos_y[i, k]))
            total += (-0.5 * ((float(ranges[e]) - d) / sigma) ** 2
                      - math.log(math.sqrt(2 * math.pi) * sigma)
                      + float(log_w[j, k]))
        worst = max(worst, abs(total - float(out[i, k])) / max(1.0, abs(total)))
print(worst)

# the conv and the tracker route receiver-sorted edges through the kernel
import tg_nebp.nn.conv.particle_bp_conv as conv_module
from torch_geometric import EdgeIndex
from tg_nebp import ParticleBPConv
conv_module.fused_bp_available = lambda tensor: True
particles = torch.stack([pos_x, pos_y, pos_x, pos_y], -1).to(device)
edges = EdgeIndex(torch.stack([src, dst]).to(device),
                  sparse_size=(num_nodes, num_nodes), sort_order='col')
conv = ParticleBPConv()
# (random edges may hold self-loops: the kernel allows them, validation not)
fused, messages = conv(particles, log_w.to(device), edges, ranges.to(device),
                       return_messages=False, validate=False)
plain, _ = conv(particles, log_w.to(device), edges.as_subclass(torch.Tensor),
                ranges.to(device), validate=False)
assert messages is None
print(float((fused - plain).abs().max() / plain.abs().max()))
'''


def test_fused_kernel_matches_loop_reference():
    device = 'cuda' if torch.cuda.is_available() else 'cpu'
    env = dict(os.environ)
    if device == 'cpu':
        env['TRITON_INTERPRET'] = '1'
    result = subprocess.run([sys.executable, '-c', SCRIPT, device],
                            capture_output=True, text=True, env=env,
                            timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    kernel_error, conv_error = map(float, result.stdout.split()[-2:])
    assert math.isfinite(kernel_error) and kernel_error < 1e-5, kernel_error
    assert math.isfinite(conv_error) and conv_error < 1e-5, conv_error
