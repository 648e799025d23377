"""mi_twopass.seeds: the stream seeds every prepass derives from the render's seed."""
from mi_twopass.seeds import hash31, splitmix64


def test_splitmix64_matches_the_reference_sequence():
    # the first two outputs of Vigna's splitmix64.c from state 0 (its state advances by the
    # golden gamma, so the second output is the first of seed 0x9E3779B97F4A7C15)
    assert splitmix64(0) == 0xE220A8397B1DCDAF
    assert splitmix64(0x9E3779B97F4A7C15) == 0x6E789E6AA1B965F4


def test_hash31_is_a_31_bit_seed_that_separates_streams():
    seeds = {hash31(s, salt, extra) for s in range(8) for salt in range(8) for extra in range(4)}
    assert len(seeds) == 8 * 8 * 4
    assert all(0 <= v < 2**31 for v in seeds)
    assert hash31(7, 3) == hash31(7, 3, 0)


def test_numpy_rng_is_one_stream_per_seed_and_salt():
    import numpy as np

    from mi_twopass.seeds import numpy_rng

    a = numpy_rng(7, 0x9E).random(16)
    assert np.array_equal(a, numpy_rng(7, 0x9E).random(16))  # same seed and salt: same stream
    assert not np.array_equal(a, numpy_rng(7, 0x9F).random(16))  # another salt
    assert not np.array_equal(a, numpy_rng(8, 0x9E).random(16))  # another seed
    # the construction the prepasses have always used (their streams stay bit for bit)
    ref = np.random.default_rng(np.random.SeedSequence([7, 0x9E])).random(16)
    assert np.array_equal(a, ref)
