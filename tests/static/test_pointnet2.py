"""PointNet++ surrogate network (the PointNet++ paper) in plain torch: the neighbourhood operations
against brute-force references, the per-mesh hierarchy, and the network's behaviour
(shapes, permutation equivariance, exact hard boundary values, learning, save/load)."""

import json
import time

import numpy as np
import pytest
import torch

from toolkit.common.phantoms.phantom import face_hex
from toolkit.static.boundary import BoundaryConditions, NodeType
from toolkit.static.pointnet2 import (
    BoundaryTargets,
    PointHierarchy,
    PointNet2,
    PointNet2Config,
    ball_query,
    enforce_boundary,
    farthest_point_sampling,
    three_nn,
    three_nn_interpolate,
)

#: a narrow network for fast tests; the neighbourhoods are the coarse-mesh defaults
SMALL = PointNet2Config.coarse(
    in_channels=9,
    sa_widths=((16, 16, 32), (32, 32, 64), (64, 64, 128), (128, 128, 128)),
    fp_widths=((128, 128), (128, 64), (64, 64), (64, 64)),
    head_width=64,
)


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _face_like_cloud(n, seed):
    """Random points in a face-sized box, mm (116 x 58 x 100, like the phantom)."""
    return np.random.default_rng(seed).uniform(0, 1, (n, 3)) * [116.0, 58.0, 100.0]


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


# ----------------------------------------------------------------------------------------------
# Neighbourhood operations against brute force
# ----------------------------------------------------------------------------------------------

def _fps_reference(x, m, start):
    chosen = [start]
    dist = ((x - x[start]) ** 2).sum(1)
    for _ in range(m - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, ((x - x[chosen[-1]]) ** 2).sum(1))
    return np.array(chosen)


def test_fps_picks_the_farthest_point_at_every_step():
    """Each sample maximises the distance to the samples before it (brute-force numpy
    reference, three batch entries with their own starts), and no point repeats."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (3, 300, 3))
    starts = torch.tensor([0, 17, 299])
    got = farthest_point_sampling(torch.from_numpy(x), 40, starts).numpy()
    for b in range(3):
        np.testing.assert_array_equal(got[b], _fps_reference(x[b], 40, int(starts[b])))
        assert np.unique(got[b]).size == 40
        d = np.sqrt(((x[b][:, None] - x[b][None, got[b]]) ** 2).sum(-1))  # (n, m)
        for i in range(1, 40):
            assert d[got[b][i], :i].min() == pytest.approx(d[:, :i].min(1).max(), rel=1e-12)


def test_ball_query_is_the_nearest_points_inside_the_radius():
    """Brute force: each group holds the min(k, count) nearest points within the radius,
    nearest first, padded with the nearest; a centre that is a point finds itself first."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (400, 3))
    centers = x[rng.choice(400, 50, replace=False)]
    radius, k = 0.35, 16
    got = ball_query(torch.from_numpy(x), torch.from_numpy(centers), radius, k).numpy()
    d = np.sqrt(((centers[:, None] - x[None]) ** 2).sum(-1))
    for c in range(50):
        inside = np.flatnonzero(d[c] <= radius)
        expect = inside[np.argsort(d[c, inside], kind="stable")][:k]
        np.testing.assert_array_equal(got[c, :expect.size], expect)
        assert np.all(got[c, expect.size:] == expect[0])
        assert d[c, got[c, 0]] == 0.0


@pytest.mark.parametrize("n, radius", [(1, 0.3), (2, 0.0), (5, 0.0), (5, 1e-9), (7, 10.0), (300, 0.0)])
def test_ball_query_never_indexes_out_of_range(n, radius):
    """Radius 0, tiny clouds (fewer points than the group size) and centres far outside the
    cloud: every index is valid, and with radius 0 a centre's group is only itself."""
    x = torch.from_numpy(np.random.default_rng(n).uniform(-1, 1, (2, n, 3)))
    far = x[:, :1] + 100.0
    for centers in (x, far):
        idx = ball_query(x, centers, radius, 32)
        assert idx.shape == (2, centers.shape[1], 32)
        assert idx.min() >= 0 and idx.max() < n
    if radius == 0.0:
        assert torch.equal(ball_query(x, x, 0.0, 32), torch.arange(n).view(1, n, 1).expand(2, n, 32))


def test_three_nn_weights_are_a_partition_of_unity():
    """Inverse-distance weights: non-negative, summing to 1, on the 3 nearest references;
    a constant field is reproduced, and a point on a reference takes its value exactly."""
    rng = np.random.default_rng(2)
    ref = torch.from_numpy(rng.uniform(-1, 1, (2, 60, 3)))
    query = torch.cat([torch.from_numpy(rng.uniform(-1, 1, (2, 200, 3))), ref[:, :20]], dim=1)
    idx, w = three_nn(query, ref)
    assert idx.shape == w.shape == (2, 220, 3)
    assert torch.all(w >= 0)
    torch.testing.assert_close(w.sum(-1), torch.ones(2, 220, dtype=torch.float64), rtol=0, atol=1e-12)
    d = ((query[:, :, None] - ref[:, None]) ** 2).sum(-1)
    torch.testing.assert_close(torch.gather(d, 2, idx), d.sort(-1).values[..., :3], rtol=0, atol=0)

    values = torch.from_numpy(rng.normal(size=(2, 60, 4)))
    constant = torch.full((2, 60, 4), 3.7, dtype=torch.float64)
    torch.testing.assert_close(three_nn_interpolate(constant, idx, w), torch.full((2, 220, 4), 3.7,
                                                                                 dtype=torch.float64))
    assert torch.equal(three_nn_interpolate(values, idx, w)[:, 200:], values[:, :20])


def test_three_nn_with_fewer_than_three_references():
    """One or two references: the missing neighbours repeat the nearest with weight 0."""
    ref = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
    idx, w = three_nn(torch.tensor([[0.25, 0, 0]]), ref)
    assert idx.tolist() == [[0, 1, 0]]
    torch.testing.assert_close(w, torch.tensor([[0.9, 0.1, 0.0]]))
    idx, w = three_nn(torch.tensor([[5.0, 1, 1]]), ref[:1])
    assert idx.tolist() == [[0, 0, 0]] and w.tolist() == [[1.0, 0.0, 0.0]]


# ----------------------------------------------------------------------------------------------
# The hierarchy of one mesh
# ----------------------------------------------------------------------------------------------

def test_hierarchy_of_the_coarse_face(phantom):
    """Level sizes quarter, every index is in range, groups start at their own centre, the
    normalised mesh fills [-1, 1] along its longest axis, and the mouth slit's coincident
    nodes are counted."""
    h = PointHierarchy.build(phantom.mesh.points, PointNet2Config.coarse())
    n = phantom.mesh.n_points
    assert h.sizes == (n, 193, 49, 13, 4)
    for level in range(h.n_levels):
        fine, coarse = h.sizes[level], h.sizes[level + 1]
        assert h.groups[level].shape == (coarse, 32) and 0 <= h.groups[level].min() and h.groups[level].max() < fine
        assert torch.equal(h.groups[level][:, 0], h.sample[level])
        assert h.interp_index[level].shape == (fine, 3) and h.interp_index[level].max() < coarse
        assert h.offsets[level].abs().max() <= 1.0 + 1e-6  # offsets are in radii
    x = h.xyz[0].double()
    torch.testing.assert_close(x * h.scale + h.center, torch.tensor(phantom.mesh.points), rtol=0, atol=1e-4)
    assert x.abs().max() == pytest.approx(1.0, abs=1e-6)
    lip_pairs = BoundaryConditions.from_mesh(phantom.mesh, phantom.segments).upper_lip.size
    assert h.n_coincident == n - np.unique(phantom.mesh.points, axis=0).shape[0] >= lip_pairs


def test_hierarchy_of_a_permuted_mesh_is_the_same_hierarchy_reindexed(phantom):
    """The face is a structured grid, full of equal distances: ties are broken by the
    points' coordinates, not their index, so the permuted mesh gives the same centres,
    offsets and interpolation weights, and the same groups up to which copy of a
    coincident node (mouth slit) they hold."""
    config = PointNet2Config.coarse()
    points = phantom.mesh.points
    perm = np.random.default_rng(3).permutation(len(points))
    a = PointHierarchy.build(points, config)
    b = PointHierarchy.build(points[perm], config)
    _, first_copy = np.unique(points, axis=0, return_inverse=True)
    copy = torch.from_numpy(first_copy.reshape(-1))
    for level in range(a.n_levels):
        assert torch.equal(a.xyz[level + 1], b.xyz[level + 1])
        assert torch.equal(a.offsets[level], b.offsets[level])
        if level == 0:
            to_a = torch.from_numpy(perm)
            assert torch.equal(copy[a.groups[0]], copy[to_a[b.groups[0]]])
            assert torch.equal(a.interp_index[0][to_a], b.interp_index[0])
            assert torch.equal(a.interp_weight[0][to_a], b.interp_weight[0])
        else:
            assert torch.equal(a.groups[level], b.groups[level])
            assert torch.equal(a.interp_weight[level], b.interp_weight[level])


def test_hierarchy_and_model_save_load_round_trip(tmp_path, phantom):
    """Config (JSON), weights and hierarchy (plain tensors) in one file, loaded with
    ``weights_only=True``, give bitwise the same outputs."""
    config = SMALL
    h = PointHierarchy.build(phantom.mesh.points, config)
    torch.manual_seed(0)
    model = PointNet2(config)
    model.train()
    model(torch.rand(4, h.n_points, 9), h)  # non-trivial batch-norm running statistics
    model.eval()
    path = tmp_path / "model.pt"
    torch.save({"config": json.dumps(config.to_dict()), "model": model.state_dict(), "hierarchy": h.state_dict()}, path)

    saved = torch.load(path, weights_only=True)
    config2 = PointNet2Config.from_dict(json.loads(saved["config"]))
    assert config2 == config
    model2 = PointNet2(config2)
    model2.load_state_dict(saved["model"])
    model2.eval()
    h2 = PointHierarchy.from_state_dict(saved["hierarchy"])
    assert h2.fingerprint() == h.fingerprint()
    x = torch.rand(2, h.n_points, 9)
    with torch.no_grad():
        assert torch.equal(model(x, h), model2(x, h2))


# ----------------------------------------------------------------------------------------------
# The network
# ----------------------------------------------------------------------------------------------

def test_output_has_a_3_vector_per_node(phantom):
    """(B, n, C) features -> (B, n, 3), finite; the default (paper-size) widths build too."""
    h = PointHierarchy.build(phantom.mesh.points, SMALL)
    out = PointNet2(SMALL)(torch.rand(3, h.n_points, 9), h)
    assert out.shape == (3, phantom.mesh.n_points, 3) and torch.isfinite(out).all()
    assert sum(p.numel() for p in PointNet2(PointNet2Config()).parameters()) == 968_131


def test_permuting_the_nodes_permutes_the_output():
    """Permutation equivariance: the hierarchy built on the permuted nodes and the permuted
    features give the permuted output (eval mode, to float32 round-off)."""
    points = _face_like_cloud(600, seed=4)
    perm = np.random.default_rng(5).permutation(600)
    config = PointNet2Config.coarse(in_channels=9)
    torch.manual_seed(1)
    model = PointNet2(config).eval()
    x = torch.rand(2, 600, 9)
    with torch.no_grad():
        out = model(x, PointHierarchy.build(points, config))
        out_perm = model(x[:, perm], PointHierarchy.build(points[perm], config))
    torch.testing.assert_close(out_perm, out[:, perm], rtol=0, atol=1e-6 * out.abs().max().item())


def test_folding_the_batch_norms_keeps_the_output():
    """In eval mode a batch norm is an affine map per channel, folded into the linear layers
    before it: after a few training steps (non-trivial running statistics and affine
    parameters) the folded copy gives the same output to float32 round-off, holds no batch
    norm, and the original still trains."""
    points = _face_like_cloud(600, seed=6)
    config = PointNet2Config.coarse(in_channels=9)
    torch.manual_seed(2)
    model = PointNet2(config)
    h = PointHierarchy.build(points, config)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(5):
        loss = model(torch.rand(4, 600, 9), h).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    folded = model.fold_batch_norm()
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in folded.modules())
    assert sum(isinstance(m, torch.nn.BatchNorm1d) for m in model.modules()) == 22
    x = torch.rand(2, 600, 9)
    with torch.no_grad():
        ref, out = model(x, h), folded(x, h)
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-5 * ref.abs().max().item())
    model.train()
    model(x, h).sum().backward()  # the original keeps its batch norms and trains


@pytest.mark.parametrize("batch_norm", [True, False])
def test_the_numpy_network_gives_the_torch_output(batch_norm):
    """:class:`PointNet2Inference` reads a trained network's state dict as numpy arrays and
    runs the same forward pass (batch norms folded, float32): after a few training steps (non-
    trivial running statistics), with hard boundaries, its output equals the torch network's in
    eval mode to float32 round-off, and the boundary values are exact."""
    from toolkit.static.pointnet2_inference import HierarchyArrays, PointNet2Inference

    points = _face_like_cloud(600, seed=7)
    config = PointNet2Config.coarse(in_channels=9, hard_boundary=True, batch_norm=batch_norm, dropout=0.2)
    torch.manual_seed(3)
    model = PointNet2(config)
    h = PointHierarchy.build(points, config)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    mask, values = torch.rand(4, 600) < 0.2, torch.randn(4, 600, 3)
    for _ in range(5):
        loss = model(torch.rand(4, 600, 9), h, BoundaryTargets(mask, values)).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    x = torch.rand(3, 600, 9)
    with torch.no_grad():
        ref = model(x, h, BoundaryTargets(mask[:3], values[:3])).numpy()
    net = PointNet2Inference(config, {k: v.numpy() for k, v in model.state_dict().items()})
    for arrays in (HierarchyArrays.from_hierarchy(h),
                   HierarchyArrays.from_state({k: v.numpy() for k, v in h.state_dict().items()})):
        out = net(x.numpy(), arrays, mask[:3].numpy(), values[:3].numpy())
        assert out.dtype == np.float32 and out.shape == ref.shape
        np.testing.assert_allclose(out, ref, rtol=0, atol=1e-5 * np.abs(ref).max())
        np.testing.assert_array_equal(out[mask[:3].numpy()], values[:3].numpy()[mask[:3].numpy()])
    with pytest.raises(ValueError, match="hard_boundary=True needs mask and values"):
        net(x.numpy(), arrays)
    with pytest.raises(ValueError, match=r"features must be \(B, n=600, in_channels=9\)"):
        net(x.numpy()[:, :500], arrays, mask[:3].numpy(), values[:3].numpy())
    with pytest.raises(ValueError, match="the weights have no 'head.0.weight'"):
        PointNet2Inference(config, {k: v.numpy() for k, v in model.state_dict().items() if not k.startswith("head")})


def test_hard_boundary_values_are_exact(phantom):
    """With ``hard_boundary`` the output is exactly 0 at fixed nodes and exactly s at
    moving nodes (bitwise), per node type or per component; free nodes are the network's."""
    bc = BoundaryConditions.from_mesh(phantom.mesh, phantom.segments)
    n = bc.n_nodes
    config = PointNet2Config.coarse(in_channels=9, hard_boundary=True)
    h = PointHierarchy.build(phantom.mesh.points, config)
    model = PointNet2(config)
    s = torch.randn(2, n, 3) * 5.0
    fixed = torch.from_numpy(bc.types == NodeType.FIXED)
    moving = torch.from_numpy(bc.types == NodeType.MOVING)
    boundary = BoundaryTargets.from_types(bc.types, s)
    u = model(torch.rand(2, n, 9), h, boundary)
    assert torch.all(u[:, fixed] == 0.0)
    assert torch.equal(u[:, moving], s[:, moving])
    assert torch.all(u[:, ~(fixed | moving)] != 0.0)

    per_component = torch.zeros(1, n, 3, dtype=torch.bool)
    per_component[0, :10, 2] = True  # e.g. a caller holding one component of sliding nodes
    v = enforce_boundary(u, BoundaryTargets(per_component, torch.full((n, 3), 1.5)))
    assert torch.all(v[:, :10, 2] == 1.5) and torch.equal(v[:, :10, :2], u[:, :10, :2])

    with pytest.raises(ValueError, match="needs boundary"):
        model(torch.rand(1, n, 9), h)
    with pytest.raises(ValueError, match="hard_boundary is False"):
        PointNet2(SMALL)(torch.rand(1, n, 9), PointHierarchy.build(phantom.mesh.points, SMALL), boundary)


def test_training_learns_a_prescribed_displacement_field():
    """Gradients flow end to end: Adam fits u(x) = a * g(x), a smooth field g scaled by an
    amplitude a given per sample in the prescribed-displacement channels (s = a at every
    node), to below 15% of the targets' mean square (16 samples, 50 steps; 2-8% over
    three seeds, from over 100% untrained)."""
    torch.manual_seed(2)
    points = _face_like_cloud(256, seed=6)
    config = PointNet2Config.coarse(in_channels=6, sa_widths=((16, 16, 32), (32, 32, 64), (64, 64, 64),
                                                              (64, 64, 64)),
                                    fp_widths=((64,), (64,), (64,), (64, 64)), head_width=64)
    h = PointHierarchy.build(points, config)
    x = h.xyz[0]
    g = torch.stack([torch.sin(2 * x[:, 0]), torch.cos(2 * x[:, 1]), x[:, 0] * x[:, 2]], dim=-1)
    a = torch.linspace(-1, 1, 16).view(-1, 1, 1)
    features = torch.cat([x.expand(16, -1, -1), a.expand(16, 256, 3)], dim=-1)
    target = a * g
    model = PointNet2(config)
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    for _ in range(50):
        batch = torch.randperm(16)[:8]
        loss = torch.mean((model(features[batch], h) - target[batch]) ** 2)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    model.eval()
    with torch.no_grad():
        mse = torch.mean((model(features, h) - target) ** 2).item()
    assert mse < 0.15 * torch.mean(target ** 2).item()


def test_errors_name_the_bad_values(phantom):
    points = phantom.mesh.points
    h = PointHierarchy.build(points, SMALL)
    model = PointNet2(SMALL)
    with pytest.raises(ValueError, match=r"in_channels=9\), got \(1, 771, 6\)"):
        model(torch.rand(1, 771, 6), h)
    with pytest.raises(ValueError, match="features have 700 nodes but the hierarchy was built for a mesh of 771"):
        model(torch.rand(1, 700, 9), h)
    with pytest.raises(ValueError, match=r"radii \(0.15, 0.3, 0.6, 1.2\).*config expects 4, \(0.25, 0.5, 1.0, 2.0\)"):
        model(torch.rand(1, 771, 9), PointHierarchy.build(points, PointNet2Config()))
    with pytest.raises(ValueError, match="level 1 asks for 1024 centres but level 0 has only 771"):
        PointHierarchy.build(points, PointNet2Config(centers=(1024, 256, 64, 16)))
    with pytest.raises(ValueError, match="one entry per level"):
        PointNet2Config(radii=(0.1, 0.2))
    with pytest.raises(ValueError, match=r"points must be \(n, 3\)"):
        PointHierarchy.build(points[:, :2], SMALL)
    with pytest.raises(ValueError, match="unknown fields"):
        PointNet2Config.from_dict({"in_chanels": 9})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(phantom):
    h = PointHierarchy.build(phantom.mesh.points, SMALL)
    model = PointNet2(SMALL).eval()
    x = torch.rand(2, h.n_points, 9)
    with torch.no_grad():
        cpu = model(x, h)
        gpu = model.to("cuda")(x.cuda(), h.to("cuda"))
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-4)


def test_paper_size_forward_time(record_property):
    """A 4,100-node forward pass with the default (paper) config on one CPU thread: timed
    and reported (``-rP`` or the junit ``forward_ms`` property), not asserted."""
    points = _face_like_cloud(4100, seed=7)
    config = PointNet2Config()
    t0 = time.perf_counter()
    h = PointHierarchy.build(points, config)
    build = time.perf_counter() - t0
    model = PointNet2(config).eval()
    x = torch.rand(1, 4100, 9)
    with torch.no_grad():
        model(x, h)
        t0 = time.perf_counter()
        out = model(x, h)
        forward = time.perf_counter() - t0
    assert out.shape == (1, 4100, 3)
    record_property("forward_ms", 1e3 * forward)
    record_property("hierarchy_build_s", build)
    print(f"4,100 nodes, one thread: hierarchy {build:.2f} s, forward (batch 1, eval) {1e3 * forward:.0f} ms")
