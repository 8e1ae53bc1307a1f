import torch
from conftest import F64, feature_pairs

from cfd_torch import pair_potential
from cfd_torch.baselines import ipc_barrier, ipc_pair_barrier, sdrs_barrier, sdrs_pair_potential


def test_scalar_barriers_match_closed_forms_and_vanish_beyond_dhat():
    x = torch.tensor([0.25, 0.5, 1.0, 2.0], dtype=F64)
    torch.testing.assert_close(ipc_barrier(x, 1.0)[0], torch.tensor(0.7797905781, dtype=F64))  # ipctk value
    assert (ipc_barrier(x, 1.0)[2:] == 0).all() and (sdrs_barrier(x, 1.0)[2:] == 0).all()
    assert torch.isinf(ipc_barrier(torch.zeros(1, dtype=F64), 1.0)).all()
    torch.testing.assert_close(sdrs_barrier(x[:1], 1.0), ipc_barrier(x[:1], 1.0) / x[:1])


def test_peers_lose_the_gradient_where_ours_keeps_it():
    dhat = 1e-2
    for gap, peers_active in [(3e-3, True), (0.1, False), (10.0, False)]:
        a, b = (t.expand(5, 3, 3) for t in feature_pairs(gap)["vertex-face"])
        b = b.clone().requires_grad_(True)
        models = {
            "ipc": lambda x, y: ipc_pair_barrier(x, y, dhat=dhat),
            "sdrs": lambda x, y: sdrs_pair_potential(x, y, dhat=dhat, margin=1e-3),
            "ours": lambda x, y: pair_potential(x, y, margin=1e-3),
        }
        for name, fn in models.items():
            (g,) = torch.autograd.grad(fn(a, b).sum(), b)
            fz = -g[..., 2].sum(-1)
            if name == "ours" or peers_active:
                assert (fz > 0).all(), (name, gap, fz)  # pushes b up, away from a
            else:
                assert (g == 0).all(), (name, gap)
