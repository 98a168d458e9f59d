"""BSMS-GNN's cost options: ``model.first_level`` (no message passing below a level) and
``model.layer_norm`` (MLPs without LayerNorm)."""

import pytest
import torch
from test_models import EDGE_DIMS, random_levels
from torch import nn

from bsms.config import ConfigError
from bsms.models import BSMSGNN, EdgeSet, Level, apply_transition
from bsms.run import load_config


def _with_edges(levels: list[Level], l: int, generator: torch.Generator) -> list[Level]:
    """``levels`` with the edges of level ``l`` drawn afresh (same counts, other pairs and features)."""
    n = levels[l].down.shape[1] if levels[l].down is not None else int(levels[l].edge_sets[0].index.max()) + 1
    fresh = [EdgeSet(torch.randint(0, n, e.index.shape, generator=generator),
                     torch.randn(e.features.shape, generator=generator)) for e in levels[l].edge_sets]
    return [level._replace(edge_sets=fresh) if k == l else level for k, level in enumerate(levels)]


def test_levels_below_the_first_level_pass_no_messages():
    torch.manual_seed(0)
    model = BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, latent=16, hidden=16, first_level=1).eval()
    full = BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, latent=16, hidden=16)
    assert len(model.down_blocks) == len(model.up_blocks) == 1 and len(full.down_blocks) == 2
    g = torch.Generator().manual_seed(4)
    levels = random_levels([30, 14, 6], g)
    x = torch.randn(30, 5, generator=g)
    with torch.no_grad():
        out = model(x, levels)
        assert torch.equal(model(x, _with_edges(levels, 0, g)), out), "level 0's edges are never read"
        assert torch.equal(model(x, [levels[0]._replace(edge_sets=[])] + levels[1:]), out)
        assert not torch.allclose(model(x, _with_edges(levels, 1, g)), out, rtol=0, atol=1e-3)
        # what it computes: level 0 only encodes, pools, unpools with its skip and decodes
        v0 = model.encoder(x)
        v1 = model.down_blocks[0](apply_transition(v0, levels[0].down), levels[1].edge_sets)
        v2 = model.bottom_block(apply_transition(v1, levels[1].down), levels[2].edge_sets)
        u1 = model.up_blocks[0](apply_transition(v2, levels[1].up), levels[1].edge_sets) + v1
        expected = model.decoder(apply_transition(u1, levels[0].up) + v0)
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-6)
    model.train()
    model(x, levels).square().sum().backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name
    with pytest.raises(ValueError, match=r"^first_level must lie in \[0, n_levels\) = \[0, 3\), got 3$"):
        BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, first_level=3)


def test_the_default_core_keeps_its_state_dict_keys():
    full = BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, latent=8, hidden=8)
    assert {k.split(".")[0] + "." + k.split(".")[1] for k in full.state_dict() if k.startswith("down_blocks")} == \
        {"down_blocks.0", "down_blocks.1"}


def test_without_layer_norm_no_mlp_normalises():
    lean = BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, latent=8, hidden=8, layer_norm=False)
    full = BSMSGNN(5, 2, EDGE_DIMS, n_levels=3, latent=8, hidden=8)
    norms = [m for m in lean.modules() if isinstance(m, nn.LayerNorm)]
    assert not norms and sum(isinstance(m, nn.LayerNorm) for m in full.modules()) == 1 + 5 * 3  # encoder + 5 blocks x 3 MLPs
    linear = [(m.in_features, m.out_features) for m in lean.modules() if isinstance(m, nn.Linear)]
    assert linear == [(m.in_features, m.out_features) for m in full.modules() if isinstance(m, nn.Linear)]


def _config(**model):
    return {"name": "lean", "dataset": {"config": "configs/datasets/press_quickstart.yaml"},
            "graph": {"levels": 4}, "model": model}


def test_config_keys_and_their_errors():
    config = load_config(_config(first_level=2, layer_norm=False))
    assert config.model.core_options(2) == {"transition": "bistride", "layer_norm": False, "first_level": 2}
    with pytest.raises(ConfigError, match=r"^config key 'model.first_level' must be below 'graph.levels' \(4\): the "
                                          r"coarsest level always passes messages; got 4$"):
        load_config(_config(first_level=4))
    with pytest.raises(ConfigError, match=r"^config key 'model.first_level' must be >= 0, got -1$"):
        load_config(_config(first_level=-1))
    with pytest.raises(ConfigError, match=r"^config key 'model.layer_norm' applies to bsms_gnn only; leave it at "
                                          r"true for meshgraphnets$"):
        load_config(_config(name="meshgraphnets", layer_norm=False))
    with pytest.raises(ConfigError, match=r"^config key 'model.first_level' applies to bsms_gnn only; leave it at "
                                          r"0 for graph_unets$"):
        load_config(_config(name="graph_unets", first_level=1))
