"""uavmeta.nn: a saved Q-network as a torch.nn.Module, fine-tuned in PyTorch and saved back where
the command line reads it."""

import numpy as np
import pytest

import uavmeta
from conftest import CONFIG
from test_evaluate import cli_line

torch = pytest.importorskip("torch")
import uavmeta.nn  # noqa: E402


def test_a_checkpoint_loads_as_a_module_with_the_numpy_policys_q_values(trained):
    net = uavmeta.nn.load_q_network(trained)
    assert isinstance(net, torch.nn.Module) and net.meta["algorithm"] == "cql"
    assert "[world]" in net.config_toml
    env = uavmeta.VectorEnv(64, config=CONFIG, task="lambda-300", normalised=True)
    obs, _ = env.reset(seed=0)
    for _ in range(30):
        obs, *_ = env.step(env.action_space.sample())
    numpy_policy = uavmeta.policies.checkpoint(env, trained)
    with torch.no_grad():
        q = net(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(q, numpy_policy.q_values(obs), rtol=1e-5, atol=1e-4)
    assert (net.act(obs) == numpy_policy(obs)).mean() > 0.95  # near ties aside


def test_a_fine_tuned_network_saves_where_uavmeta_eval_reads_it(trained, run_cli, tmp_path):
    net = uavmeta.nn.load_q_network(trained)
    optimiser = torch.optim.SGD(net.parameters(), lr=1e-3)
    loss = net(torch.rand(8, 12)).pow(2).mean()  # one step of anything: the weights move
    loss.backward()
    optimiser.step()
    out = uavmeta.nn.save_q_network(net, tmp_path / "tuned", epoch=61)
    again = uavmeta.nn.load_q_network(out)
    for a, b in zip(net.state_dict().values(), again.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert again.meta["epoch"] == 61 and again.meta["world_hash"] == net.meta["world_hash"]
    cli = run_cli("eval", "--config", CONFIG, "--task", "lambda-300", "--checkpoint", out).stdout
    env = uavmeta.UavEnv.from_config(CONFIG, task="lambda-300", normalised=True)
    score = uavmeta.evaluate(uavmeta.policies.checkpoint(env, out), env, trapped=False)
    assert cli_line("return", score.ret, 1) in cli, cli


def test_bad_checkpoints_raise_errors_naming_them(tmp_path):
    with pytest.raises(TypeError, match="path = None"):
        uavmeta.nn.load_q_network(None)
    with pytest.raises(ValueError, match="nowhere.json"):
        uavmeta.nn.load_q_network(tmp_path / "nowhere")
    net = uavmeta.nn.QNetwork(12, 50)
    with pytest.raises(ValueError, match="expected the world it belongs to"):
        uavmeta.nn.save_q_network(net, tmp_path / "orphan")
    with pytest.raises(TypeError, match="expected a uavmeta.nn.QNetwork"):
        uavmeta.nn.save_q_network(torch.nn.Linear(2, 2), tmp_path / "x")
