//! learn-bench on a plant the compensator already tracks: learning must not make it worse. The
//! table of iteration 0 is the period the compensator settles to with the reference played in a
//! loop; a table cut from the first periods after rest jumps at its wrap (the Bouc-Wen loop still
//! moves from one period to the next), and every trial would relearn that jump.

use host_sim::learn_bench::{run_learn_bench, LearnBenchSettings, LearnMode};
use host_sim::servo_bench::Shape;

#[test]
fn learning_keeps_a_clean_plant_at_its_first_trial() {
    let settings = LearnBenchSettings {
        frequencies_hz: vec![10.0],
        shapes: vec![Shape::Sine],
        modes: vec![LearnMode::LearnedFeedback],
        iterations: 4,
        // No creep, drift, noise or quantisation: with feedback, trial 0 is at 1e-4 % of the
        // stroke, and the table learned from it must stay there.
        plant_effects: Vec::new(),
        perturbations: Vec::new(),
        ..LearnBenchSettings::default()
    };
    let report = run_learn_bench(&settings, &mut |_| {}).unwrap();
    let curve = report
        .curve(LearnMode::LearnedFeedback, Shape::Sine, 10.0)
        .expect("the 10 Hz sine row");
    let rms = &curve.rms_percent;
    assert_eq!(rms.len(), 5);
    assert!(rms[0] < 1e-3, "trial 0: {rms:?}");
    // A base that jumps at its wrap took every later trial to ≈ 0.01 %.
    for (trial, &e) in rms.iter().enumerate() {
        assert!(e < 1e-3, "trial {trial}: {rms:?}");
    }
}
