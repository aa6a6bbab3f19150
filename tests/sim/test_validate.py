from latentdrive.sim.validate import format_throughput, measure_scaling, measure_throughput


def test_throughput_helpers_run_and_report():
    rows = [measure_throughput("merge", batch_size=4, fast_steps=3, highway_steps=3),
            measure_throughput("intersection", batch_size=2, fast_steps=2, highway_steps=2)]
    assert all(r.highway_steps_per_s > 0 and r.fast_steps_per_s > 0 and not r.velocity_maps for r in rows)
    assert "speed-up" in format_throughput(rows)
    scaling = measure_scaling(counts=(12, 30), batch_size=2, steps=3)
    assert [n for n, _ in scaling] == [14, 32] and all(rate > 0 for _, rate in scaling)
