import numpy as np

from common.normalizer import RunningMeanStd


def test_batched_updates_equal_numpy_over_all_data():
    rng = np.random.default_rng(0)
    data = rng.normal(3.0, 2.0, size=(1000, 5))
    rms = RunningMeanStd((5,))
    for chunk in np.array_split(data, [1, 7, 300, 301, 640]):
        rms.update(chunk)
    np.testing.assert_allclose(rms.mean, data.mean(0), rtol=1e-10)
    np.testing.assert_allclose(rms.var, data.var(0), rtol=1e-10)
    assert rms.count == 1000


def test_normalize_clips_and_state_round_trips():
    rms = RunningMeanStd((2,), clip=5.0)
    rms.update(np.array([[0.0, 0.0], [2.0, 4.0]]))
    z = rms.normalize(np.array([1.0, 1000.0]))
    np.testing.assert_allclose(z, [0.0, 5.0], atol=1e-6)
    other = RunningMeanStd((2,))
    other.load_state_dict(rms.state_dict())
    np.testing.assert_array_equal(other.normalize([3.0, -3.0]), rms.normalize([3.0, -3.0]))
