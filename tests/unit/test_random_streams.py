"""RandomStreams: bound to the global generators until detached; detached copies draw what the globals would have
drawn, apart from them; installed() lends them to code that draws from the globals and keeps what it drew."""

import pickle
import random

import numpy as np
import torch as th
from stable_baselines3.common.noise import NormalActionNoise

from sb3_td3x import TD3X
from sb3_td3x.common.random_streams import RandomStreams, detached_streams


def draw(streams: RandomStreams) -> tuple:
    """One number from each stream, as TD3X's code draws them."""
    return (
        streams.python.random(),
        streams.numpy.randint(0, 1000, size=3).tolist(),
        th.randn(3, generator=streams.torch(th.device("cpu"))).tolist(),
    )


def draw_globals() -> tuple:
    return random.random(), np.random.randint(0, 1000, size=3).tolist(), th.randn(3).tolist()


def numpy_position(streams: RandomStreams) -> tuple:
    """Where a numpy stream stands: its MT19937 key and the position in it."""
    state = streams.state()["numpy"]
    return state[1].tolist(), state[2], state[3], state[4]


def seed_globals(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    th.manual_seed(seed)


def test_bound_streams_are_the_global_generators():
    seed_globals(1)
    expected = [draw_globals(), draw_globals()]
    seed_globals(1)
    streams = RandomStreams()
    assert [draw(streams), draw_globals()] == expected  # one stream: the two draw in turn
    with streams.installed():  # nothing to install
        assert streams.bound


def test_detached_streams_go_on_where_the_globals_stood_and_leave_them_alone():
    seed_globals(2)
    expected = [draw_globals() for _ in range(3)]
    seed_globals(2)
    streams = RandomStreams().detach()
    seed_globals(99)  # the caller's draws no longer touch the streams, and theirs no longer touch the caller's
    caller = draw_globals()
    assert [draw(streams) for _ in range(3)] == expected
    seed_globals(99)
    assert draw_globals() == caller


def test_installed_lends_the_streams_to_the_globals_and_keeps_what_was_drawn():
    seed_globals(3)
    expected = [draw_globals() for _ in range(3)]
    seed_globals(3)
    streams = RandomStreams().detach()
    seed_globals(7)
    caller = RandomStreams().state()
    first = draw(streams)
    with streams.installed():
        assert draw_globals() == expected[1]  # foreign code drawing from the globals draws the stream's numbers
        assert draw(streams) == expected[2]  # and the model's own code goes on in the same stream
        with streams.installed():  # nested: nothing more to do
            pass
    assert first == expected[0]
    after = RandomStreams().state()  # the caller's globals put back
    assert np.array_equal(after["numpy"][1], caller["numpy"][1]) and th.equal(after["torch"], caller["torch"])
    seed_globals(3)
    [draw_globals() for _ in range(3)]
    assert draw(streams) == draw_globals()  # the stream goes on after what was drawn while installed


def test_state_round_trips_and_pickles():
    streams = RandomStreams().detach()
    state = pickle.loads(pickle.dumps(streams.state()))
    expected = draw(streams)
    streams.set_state(state)
    assert draw(streams) == expected


def test_a_td3x_draws_its_noise_and_indices_from_its_streams(tmp_path):
    """Detached, a model's replay indices and NormalActionNoise come from its streams, not from the globals; its
    streams are not saved, and a loaded model's are the global generators again."""
    noise = NormalActionNoise(np.zeros(1), 0.1 * np.ones(1))
    model = TD3X(
        "MlpPolicy",
        "Pendulum-v1",
        learning_starts=50,
        batch_size=8,
        policy_kwargs={"net_arch": [8]},
        seed=0,
        action_noise=noise,
    )
    model.learn(60)
    streams = detached_streams(model)
    assert streams is model.random_streams and not streams.bound
    before = numpy_position(RandomStreams())
    model.learn(30, reset_num_timesteps=False)  # installed for the call: the globals are put back after
    assert numpy_position(RandomStreams()) == before
    own = numpy_position(streams)
    model.replay_buffer.sample(4)
    model._own_stream_noise(noise)()
    assert numpy_position(streams) != own  # drawn from the model's own stream
    assert numpy_position(RandomStreams()) == before  # not from the global one
    model.save(tmp_path / "model.zip")
    assert TD3X.load(tmp_path / "model.zip").random_streams.bound
