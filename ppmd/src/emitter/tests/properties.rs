//! Properties of the loop, each checked on any commands, stalls and late
//! wake-ups as every modelled receiver decodes the line; and the examples
//! they found. Their regression seeds are in
//! `proptest-regressions/emitter/tests/properties.txt`.

use super::*;
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;

/// A scenario of the property below: grid or follow timing; commands
/// as (ms after the previous one, first value); stalls as (ms after the
/// start, us long); how late every sleep wakes; the failsafe action.
type Scenario = (bool, Vec<(u64, u64)>, Vec<(u64, u64)>, u64, FailsafeAction);

/// Runs a scenario on the simulated clock and checks what every
/// receiver reads (see the property).
fn check_scenario(scenario: Scenario) -> Result<(), TestCaseError> {
    check_expired_scenario(scenario, None, 0)
}

/// [`check_scenario`] with expired commands among the fresh ones: with
/// `history`, a sample received that many ms before the loop started
/// is there from the start (as a service's history offers the last
/// command of an earlier run); with `every` > 0, every `every`-th
/// command was received 101 ms to 3 s before it was published (older
/// than the 100 ms failsafe limit). Expired commands carry odd first
/// values and fresh ones even, so a frame with an odd value flew an
/// expired command.
fn check_expired_scenario(
    (follow, cmds, stalls, late_us, action): Scenario,
    history: Option<u64>,
    every: usize,
) -> Result<(), TestCaseError> {
    let model = timed_model(follow, "");
    let sim = scenario_sim(&stalls, late_us);
    let expired = |k: usize| every > 0 && k % every == every - 1;
    let cmds: Vec<(u64, u64)> = cmds
        .iter()
        .enumerate()
        .map(|(k, &(gap, v))| {
            (
                gap,
                if expired(k) {
                    (v | 1).min(1_999)
                } else {
                    v & !1
                },
            )
        })
        .collect();
    let mut src = scenario_feed(&sim, &model, &cmds);
    let mut aged = 0;
    for (k, c) in src.cmds.iter_mut().enumerate() {
        if expired(k) {
            c.2.recv_mono_ns = c.0 - (101 + (c.0 / MS) % 2_900) * MS;
            aged += 1;
        }
    }
    if let Some(age_ms) = history {
        let mut old = sample(&model, b"[1999, 1900]", 1);
        old.recv_mono_ns = START_NS - age_ms * MS;
        src.cmds.insert(0, (START_NS, 1_999, old));
    }
    let until_ms = (src.last_at() - START_NS) / MS + 150;
    let mut out = Recorder::default();
    let stats = run_one(
        &sim,
        &model,
        scenario_cfg(action),
        &mut src,
        LineRef::Edges(&mut out),
        until_ms,
    );
    let fresh: Vec<(u64, u32)> = src.made().into_iter().filter(|m| m.1 % 2 == 0).collect();
    // A stall can make a fresh command expire before the loop takes it
    // (or, at the very start, come before the loop started): only
    // without stalls is every refused command an aged one.
    let refused = stats.expired.load(Relaxed);
    let most = if stalls.is_empty() { aged } else { u64::MAX };
    prop_assert!(
        refused >= history.is_some() as u64 && refused - history.is_some() as u64 <= most,
        "{refused} refused of {aged} aged commands and {history:?}"
    );
    check_output(&model, &out.edges, &stats, &fresh)
}

/// A simulated clock with these stalls (ms after the start, us long)
/// and every sleep `late_us` late.
pub(super) fn scenario_sim(stalls: &[(u64, u64)], late_us: u64) -> Sim {
    let sim = Sim::new();
    sim.set_wake_late_ns(late_us * 1_000);
    for (at_ms, us) in stalls {
        sim.stall_at(START_NS + at_ms * MS, us * 1_000);
    }
    sim
}

/// Commands (ms after the previous one, first value) as `[v, 1900]`.
pub(super) fn scenario_feed(sim: &Sim, model: &FrameModel, cmds: &[(u64, u64)]) -> Feed {
    let mut t = START_NS;
    let cmds: Vec<(u64, String)> = cmds
        .iter()
        .map(|(gap_ms, v)| {
            t += gap_ms * MS;
            (t, format!("[{v}, 1900]"))
        })
        .collect();
    let cmds: Vec<(u64, &str)> = cmds.iter().map(|(t, c)| (*t, c.as_str())).collect();
    Feed::new(sim, model, &cmds)
}

/// The automatic margin and a 100 ms failsafe with `action`.
fn scenario_cfg(action: FailsafeAction) -> Settings {
    Settings {
        margin: Margin::Auto {
            min_ns: 20_000,
            max_ns: 500_000,
        },
        ..cfg(100, action)
    }
}

/// Checks one output's waveform (see the property below); `made`: its
/// commands (published at, first value).
fn check_output(
    model: &FrameModel,
    edges: &[TraceEdge],
    stats: &Stats,
    made: &[(u64, u32)],
) -> Result<(), TestCaseError> {
    let values: Vec<u64> = made.iter().map(|m| m.1 as u64).collect();
    prop_assert!(
        edges.iter().all(|e| e.actual_ns >= e.scheduled_ns),
        "never early"
    );
    let frames = sent_frames(edges, model.channels());
    let aborted = stats.aborted_frames.load(Relaxed);
    let whole = frames.iter().filter(|f| !f.aborted).count() as u64;
    let cut = frames.len() as u64 - whole;
    // Every frame is logged whole (or glitched) or aborted; an aborted
    // frame shows on the line as a short one, or not at all when it was
    // aborted at its first pulse.
    prop_assert_eq!(whole, stats.frames.load(Relaxed) - aborted);
    prop_assert!(cut <= aborted, "{} cut frames, {} aborted", cut, aborted);
    let lead_ins = frames.iter().filter(|f| f.after_lead_in).count() as u64;
    let pulses: u64 = frames.iter().map(|f| f.values_us.len() as u64 + 1).sum();
    prop_assert_eq!(edges.len() as u64, 2 * pulses + 2 * lead_ins);
    prop_assert_eq!(stats.edges.load(Relaxed), edges.len() as u64);
    prop_assert!(
        lead_ins
            <= 1 + stats.overruns.load(Relaxed) + stats.failsafe_entries.load(Relaxed) + aborted,
        "{lead_ins} lead-ins, {stats:?}"
    );
    // The syncs: a frame follows its predecessor's last pulse (an
    // aborted one's too) by a sync, or a lone pulse LEAD_IN_NS before
    // it (which itself follows the last pulse by more than any channel).
    let (lo, hi) = match model.timing() {
        Timing::Grid => model.sync_window_ns(),
        Timing::Follow => (model.follow_sync_ns().0, us_to_ns(FOLLOW_SYNC_CEILING_US)),
    };
    for (i, f) in frames.iter().enumerate() {
        match (f.after_lead_in, f.before) {
            // A lone pulse: a lead-in whose frame was aborted at once.
            _ if f.values_us.is_empty() => prop_assert!(f.aborted),
            (false, Some(b)) => {
                let sync = f.start - b;
                prop_assert!((lo..=hi).contains(&sync), "frame {}: sync {} ns", i, sync);
            }
            (false, None) => prop_assert!(false, "the first frame without a lead-in"),
            (true, _) => {}
        }
        // Values: a command's first value (or the default), then
        // 1900 (or the default), then the defaults; an aborted frame
        // the first of them.
        let default_us = |c: usize| u64::from(model.default_ns(c)) / 1_000;
        let want_rest: Vec<u64> = (2..model.channels()).map(default_us).collect();
        let v = &f.values_us;
        let first = |c: usize, want: u64| v.get(c).is_none_or(|&x| x == want);
        let cmd = v.first().is_none_or(|x| values.contains(x)) && first(1, 1_900);
        let defaults = first(0, default_us(0)) && first(1, default_us(1));
        prop_assert!(cmd || defaults, "frame {}: {:?}", i, v);
        let rest = v.get(2..).unwrap_or(&[]);
        prop_assert_eq!(rest, &want_rest[..rest.len()], "frame {}", i);
    }
    // A trainer input reads every frame that carried a channel, an
    // aborted one as a short frame with the channels before the abort.
    let carried: Vec<&Sent> = frames.iter().filter(|f| !f.values_us.is_empty()).collect();
    for r in [Receiver::EdgeTx, Receiver::OpenTx] {
        let (read, _) = decode_as(r, scheduled(edges), Level::High);
        prop_assert_eq!(read.len(), carried.len(), "{:?}", r);
        for (got, f) in read.iter().zip(&carried) {
            prop_assert_eq!(got.start_ns, f.start);
            prop_assert_eq!(&got.channels_us()[..], &f.values_us[..]);
        }
    }
    // A flight controller hands a frame on at the sync after it (not
    // the last one), once locked on (a lead-in pulse or an aborted
    // frame before it locks can make it start over): from the first
    // frame it hands on, every frame it takes but the last, exactly
    // (Betaflight drops an aborted frame, its channel count is not the
    // locked one; ArduPilot takes one of 5 channels or more); and it
    // locks after its warm-up when no lead-in or abort comes in between.
    for r in [Receiver::Betaflight, Receiver::ArduPilot] {
        let takes = |f: &Sent| match r {
            Receiver::Betaflight => !f.aborted,
            _ => f.values_us.len() >= 5,
        };
        let (read, _) = decode_as(r, scheduled(edges), Level::High);
        let Some(first) = read.first() else {
            // Its count starts over at a frame after a lead-in, or
            // after an aborted frame; from there it hands on the frame
            // after its warm-up at the sync that follows it.
            let restart = frames
                .iter()
                .enumerate()
                .filter_map(|(k, f)| match (f.aborted, f.after_lead_in) {
                    (true, _) => Some(k + 1),
                    (false, true) => Some(k),
                    _ => None,
                })
                .max()
                .unwrap_or(0);
            prop_assert!(
                frames.len() - restart.min(frames.len()) <= 1 + r.warmup_frames(),
                "{:?} read none of {} frames ({} after its count last started over)",
                r,
                frames.len(),
                frames.len() - restart.min(frames.len())
            );
            continue;
        };
        let from = frames.iter().position(|f| f.start == first.start_ns);
        prop_assert!(from.is_some(), "{:?} read a frame not sent", r);
        let tail: Vec<&Sent> = frames[from.unwrap()..frames.len() - 1]
            .iter()
            .filter(|f| takes(f))
            .collect();
        prop_assert_eq!(read.len(), tail.len(), "{:?}", r);
        for (got, f) in read.iter().zip(&tail) {
            prop_assert_eq!(got.start_ns, f.start);
            prop_assert_eq!(&got.channels_us()[..], &f.values_us[..]);
        }
        let clean = frames[..=r.warmup_frames().min(frames.len() - 1)]
            .iter()
            .enumerate()
            .all(|(k, f)| !f.aborted && (k == 0 || !f.after_lead_in));
        prop_assert!(
            !clean || from == Some(r.warmup_frames()),
            "{:?} locked at {:?}",
            r,
            from
        );
    }
    Ok(())
}

/// Any failsafe action.
pub(super) fn any_action() -> impl Strategy<Value = FailsafeAction> {
    prop_oneof![
        Just(FailsafeAction::Hold),
        Just(FailsafeAction::Silence),
        Just(FailsafeAction::Default),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(
        std::env::var("PROPTEST_CASES").map_or(48, |c| c.parse().expect("a number")),
    ))]

    /// Whatever the commands' pace, stalls of the loop and late
    /// wake-ups: every edge is planned, none written early; every frame
    /// has valid syncs around it or a lead-in pulse before it; a trainer
    /// input (EdgeTX, OpenTX) reads every frame, a flight controller
    /// (Betaflight, ArduPilot) every frame after its warm-up, with the
    /// values of a command that was published (or the defaults) to the
    /// microsecond; and the counters add up.
    #[test]
    fn any_commands_stalls_and_late_wake_ups_give_frames_every_receiver_reads(
        follow in any::<bool>(),
        cmds in prop::collection::vec((1u64..60, 1_000u64..=2_000), 1..40),
        stalls in prop::collection::vec((0u64..800, 1u64..60_000), 0..4),
        late_us in 0u64..80,
        action in any_action(),
    ) {
        check_scenario((follow, cmds, stalls, late_us, action))?;
    }

    /// The same with expired commands: a sample from before the start
    /// (a service's history of an earlier run, received up to 5 s
    /// before it, or only 1 ms), and commands received longer than the
    /// failsafe limit before they were published. None of them ever
    /// flies, whatever the timing and failsafe action: the line does
    /// what the startup says until a fresh command comes, and holds
    /// only fresh ones.
    #[test]
    fn expired_commands_never_fly(
        follow in any::<bool>(),
        cmds in prop::collection::vec((1u64..60, 1_000u64..=2_000), 1..30),
        stalls in prop::collection::vec((0u64..800, 1u64..60_000), 0..3),
        late_us in 0u64..80,
        action in any_action(),
        history in prop::option::of(1u64..5_000),
        every in 0usize..4,
    ) {
        check_expired_scenario((follow, cmds, stalls, late_us, action), history, every)?;
    }

    /// The same for two outputs of one loop (8 channels at 22.5 ms and 6
    /// at 20 ms, each grid or follow, commands of their own): each
    /// output's waveform holds to it, whatever the other's edges and
    /// decisions (a decision whose time falls on an edge is made
    /// before it).
    #[test]
    fn two_outputs_of_any_commands_each_give_frames_every_receiver_reads(
        follow in (any::<bool>(), any::<bool>()),
        cmds_a in prop::collection::vec((1u64..60, 1_000u64..=2_000), 1..30),
        cmds_b in prop::collection::vec((1u64..60, 1_000u64..=2_000), 1..30),
        stalls in prop::collection::vec((0u64..800, 1u64..60_000), 0..3),
        late_us in 0u64..80,
    ) {
        let a = timed_model(follow.0, "");
        let b = timed_model(follow.1, SIX_AT_20_MS);
        let sim = scenario_sim(&stalls, late_us);
        let mut src_a = scenario_feed(&sim, &a, &cmds_a);
        let mut src_b = scenario_feed(&sim, &b, &cmds_b);
        let (made_a, made_b) = (src_a.made(), src_b.made());
        let until_ms = (src_a.last_at().max(src_b.last_at()) - START_NS) / MS + 150;
        let (mut out_a, mut out_b) = (Recorder::default(), Recorder::default());
        let silence = scenario_cfg(FailsafeAction::Silence);
        let hold = scenario_cfg(FailsafeAction::Hold);
        let (stats_a, stats_b) = run_two(
            &sim,
            (&a, silence, &mut src_a, LineRef::Edges(&mut out_a)),
            (&b, hold, &mut src_b, LineRef::Edges(&mut out_b)),
            until_ms,
        );
        check_output(&a, &out_a.edges, &stats_a, &made_a)?;
        check_output(&b, &out_b.edges, &stats_b, &made_b)?;
    }

    /// The same for three outputs on one GPIO bank (the lines of one
    /// request, written together): each line's waveform holds to it,
    /// and edges due at one time go out in one write, never two.
    #[test]
    fn three_banked_outputs_of_any_commands_each_give_frames_every_receiver_reads(
        follow in (any::<bool>(), any::<bool>(), any::<bool>()),
        cmds in prop::collection::vec(
            prop::collection::vec((1u64..60, 1_000u64..=2_000), 1..25),
            3,
        ),
        stalls in prop::collection::vec((0u64..600, 1u64..60_000), 0..3),
        late_us in 0u64..80,
    ) {
        let models = [
            timed_model(follow.0, ""),
            timed_model(follow.1, SIX_AT_20_MS),
            timed_model(follow.2, ""),
        ];
        let sim = scenario_sim(&stalls, late_us);
        let mut srcs: Vec<Feed> = models
            .iter()
            .zip(&cmds)
            .map(|(m, c)| scenario_feed(&sim, m, c))
            .collect();
        let made: Vec<Vec<(u64, u32)>> = srcs.iter().map(Feed::made).collect();
        let last = srcs.iter().map(Feed::last_at).max().unwrap();
        let until_ms = (last - START_NS) / MS + 150;
        let mut kits: [Kit; 3] = Default::default();
        let mut bank = BankRecorder::default();
        {
            let silence = scenario_cfg(FailsafeAction::Silence);
            let mut outputs: Vec<Output> = srcs
                .iter_mut()
                .zip(&models)
                .zip(kits.iter_mut())
                .enumerate()
                .map(|(i, ((source, model), kit))| {
                    let line = LineRef::Banked { bank: 0, bit: i as u32 };
                    output(model, silence, source, line, kit)
                })
                .collect();
            let mut banks: [&mut dyn Bank; 1] = [&mut bank];
            run_until(&sim, silence.margin, &mut outputs, &mut banks, until_ms);
        }
        let stats = kits.map(|k| k.stats);
        for w in bank.0.windows(2) {
            prop_assert!(w[0].0 < w[1].0, "two writes for one time: {:?}", w);
        }
        for (i, model) in models.iter().enumerate() {
            // The bank does not say when it wrote: its edges as due.
            let edges: Vec<TraceEdge> = bank
                .0
                .iter()
                .filter(|(_, m, _)| m & (1 << i) != 0)
                .map(|&(t, _, l)| TraceEdge {
                    scheduled_ns: t,
                    actual_ns: t,
                    level: Level::from_bit(l & (1 << i) != 0),
                })
                .collect();
            check_output(model, &edges, &stats[i], &made[i]).map_err(|e| {
                TestCaseError::fail(format!("output {i}: {e}; frames {:?}", sent_frames(&edges, model.channels())))
            })?;
        }
    }
}

/// Every timing, failsafe action and startup, with an expired command
/// offered first: the last command of an earlier run (received 3 s
/// before the start, or 50 ms before it: fresh by age, but not seen
/// arriving), or one received 3 s before it was published. It never
/// flies: until the fresh command at 300 ms the line does exactly what
/// the startup says (silence, or default frames), then carries the
/// fresh command, and the failsafe after it holds only that one.
#[test]
fn before_its_first_fresh_command_an_output_does_what_startup_says() {
    let old = "[1900, 1100]";
    for follow in [false, true] {
        for action in [
            FailsafeAction::Silence,
            FailsafeAction::Hold,
            FailsafeAction::Default,
        ] {
            for startup in [FailsafeAction::Silence, FailsafeAction::Default] {
                for (offered_ms, age_ms) in [(0, 3_000), (0, 50), (30, 3_000)] {
                    let case = format!(
                        "follow {follow}, {action:?}, startup {startup:?}, \
                         offered at {offered_ms} ms, {age_ms} ms old"
                    );
                    let sim = Sim::new();
                    let model = timed_model(follow, "");
                    let fresh_at = START_NS + 300 * MS;
                    let mut src = Feed::new(
                        &sim,
                        &model,
                        &[(START_NS + offered_ms * MS, old), (fresh_at, CMD)],
                    );
                    src.cmds[0].2.recv_mono_ns = src.cmds[0].0 - age_ms * MS;
                    let mut out = Recorder::default();
                    let stats = run_one(
                        &sim,
                        &model,
                        Settings {
                            failsafe: EmitterConfig {
                                startup,
                                ..cfg(100, action).failsafe
                            },
                            ..cfg(100, action)
                        },
                        &mut src,
                        LineRef::Edges(&mut out),
                        600,
                    );
                    assert_eq!(stats.expired.load(Relaxed), 1, "{case}");
                    assert_eq!(stats.commands.load(Relaxed), 1, "{case}");
                    let frames = sent_frames(&out.edges, model.channels());
                    let defaults: Vec<u64> = (0..model.channels())
                        .map(|c| u64::from(model.default_ns(c)) / 1_000)
                        .collect();
                    let (before, after): (Vec<_>, Vec<_>) =
                        frames.iter().partition(|f| f.start < fresh_at);
                    match startup {
                        FailsafeAction::Silence => {
                            assert!(before.is_empty(), "{case}: {before:?}")
                        }
                        _ => {
                            // A default frame at least every longest
                            // sync (follow) or frame (grid).
                            assert!(before.len() >= 8, "{case}: {}", before.len());
                            for f in &before {
                                assert_eq!(f.values_us, defaults, "{case}");
                            }
                        }
                    }
                    // A frame decided just before the fresh command
                    // came may start just after it.
                    let first = after
                        .iter()
                        .position(|f| f.values_us == CMD_US.to_vec())
                        .unwrap_or_else(|| panic!("{case}: the fresh command flies"));
                    assert!(first <= 1, "{case}: {first}");
                    for f in &after {
                        let held = f.values_us == CMD_US.to_vec();
                        assert!(held || f.values_us == defaults, "{case}: {:?}", f.values_us);
                    }
                    for f in &after[first..] {
                        assert!(
                            f.values_us == CMD_US.to_vec() || action == FailsafeAction::Default,
                            "{case}: {:?}",
                            f.values_us
                        );
                    }
                }
            }
        }
    }
}

/// Found by the property above: a 29.6 ms stall in the first frame
/// made the next one late; moved later by 7.1 ms it left a sync of
/// exactly 4000 us after it, which EdgeTX does not read as a sync (it
/// lost the frame after). A late frame now keeps the receivers' window
/// less the 500 us margin (4500..18500 us).
#[test]
fn a_late_frame_keeps_the_sync_margin() {
    let cmds = [15, 36, 7, 7, 39, 7, 46, 31, 52, 20, 58, 59, 47, 50, 50]
        .map(|gap| (gap, 1_000))
        .to_vec();
    check_scenario((false, cmds, vec![(17, 29_588)], 21, FailsafeAction::Hold)).unwrap();
}

/// A scenario of the late-edge property: a stamped line, follow
/// timing, idle high, channels, commands (ms after the previous one, a seed for their
/// values), stalls of the loop (ms after the start, us long), writes
/// held up (which write, us long), how late every sleep wakes, the
/// failsafe action.
type LateScenario = (
    bool,
    bool,
    bool,
    usize,
    Vec<(u64, u64)>,
    Vec<(u64, u64)>,
    Vec<(usize, u64)>,
    u64,
    FailsafeAction,
);

/// Value of channel `c` of the command made from `seed`, us.
fn seeded_us(seed: u64, c: usize) -> u64 {
    1_000 + (seed.wrapping_mul(2_654_435_761) >> (c * 3)) % 1_001
}

/// Runs a late-edge scenario with a frame log; checks what every
/// receiver reads from the times the edges reached the line, and the
/// log against it.
fn check_late_edges(
    (stamped, follow, idle_high, channels, cmds, stalls, held, late_us, action): LateScenario,
) -> Result<(), TestCaseError> {
    static CASE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    // Grid frames long enough for every channel at its maximum.
    let frame_us = channels as u64 * 2_000 + 5_000;
    let idle = if idle_high { "high" } else { "low" };
    let model = timed_model(
        follow,
        &format!("channels = {channels}\nframe_us = {frame_us}.0\nidle_level = '{idle}'"),
    );
    let guard_us = model.late_edge_guard_ns() / 1_000;
    let sim = scenario_sim(&stalls, late_us);
    let mut t = START_NS;
    let texts: Vec<(u64, String)> = cmds
        .iter()
        .map(|&(gap_ms, seed)| {
            t += gap_ms * MS;
            let v: Vec<String> = (0..channels)
                .map(|c| seeded_us(seed, c).to_string())
                .collect();
            (t, format!("[{}]", v.join(", ")))
        })
        .collect();
    let texts: Vec<(u64, &str)> = texts.iter().map(|(t, c)| (*t, c.as_str())).collect();
    let mut src = Feed::new(&sim, &model, &texts);
    // What a channel may carry: a command's value or its default.
    let allowed: Vec<Vec<u64>> = (0..channels)
        .map(|c| {
            let mut v: Vec<u64> = cmds.iter().map(|&(_, seed)| seeded_us(seed, c)).collect();
            v.push(u64::from(model.default_ns(c)) / 1_000);
            v
        })
        .collect();
    let dir = std::env::temp_dir().join(format!(
        "ppmd-late-{}-{}",
        std::process::id(),
        CASE.fetch_add(1, Relaxed)
    ));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("frames.jsonl");
    let (mut log, mut writer) = framelog::open(&path, 1 << 24).unwrap();
    let mut wire = Wire {
        sim: sim.clone(),
        edges: Vec::new(),
        held,
        stamped,
    };
    let until_ms = (src.last_at() - START_NS) / MS + 150;
    let cfg = scenario_cfg(action);
    let line = LineRef::Edges(&mut wire);
    let stats = run_logged(&sim, &model, cfg, &mut src, line, &mut log, until_ms);
    drop(log);
    writer.finish();
    let rows: Vec<serde_json::Value> = log_rows(&path)
        .into_iter()
        .filter(|r| r["type"] == "frame")
        .collect();
    std::fs::remove_dir_all(&dir).unwrap();
    // The log has a row per frame, and says which were aborted and glitched.
    let count = |status: &str| rows.iter().filter(|r| r["status"] == status).count() as u64;
    prop_assert_eq!(rows.len() as u64, stats.frames.load(Relaxed));
    prop_assert_eq!(count("aborted"), stats.aborted_frames.load(Relaxed));
    let glitched = rows.iter().filter(|r| r["glitched"] == true).count() as u64;
    prop_assert_eq!(glitched, stats.glitched_frames.load(Relaxed));
    // The line ends idle; an aborted frame leaves it idle too.
    let idle_level = model.idle_level();
    prop_assert!(wire.edges.last().is_none_or(|e| e.0.level == idle_level));
    let line: Vec<(u64, Level)> = wire
        .edges
        .iter()
        .map(|(e, real)| (*real, e.level))
        .collect();
    let offset = model.timed_offset_ns();
    for r in Receiver::ALL {
        let (read, _) = decode_as(r, line.iter().copied(), Level::High);
        for got in &read {
            // The row of the frame it read: the last one whose first
            // timed edge was due by then.
            let row = rows
                .iter()
                .rev()
                .find(|row| row["mono_ns"].as_u64().unwrap() + offset <= got.start_ns);
            prop_assert!(row.is_some(), "{:?} read a frame before the first", r);
            let row = row.unwrap();
            let logged: Vec<f64> = row["ch_us"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let v = got.channels_us();
            prop_assert!(
                v.len() <= logged.len(),
                "{:?} read {} channels of a frame logged with {}: {}",
                r,
                v.len(),
                logged.len(),
                row
            );
            if v.len() < channels && row["glitched"] == false {
                // Only an aborted frame is short (a trainer input hands
                // on what it has at the abort; the others drop it or
                // take it short), or a glitched one whose late edge
                // took a value out of the receiver's window.
                prop_assert_eq!(&row["status"], "aborted", "{:?}: {:?} {}", r, v, row);
                prop_assert_eq!(row["aborted_at"].as_u64(), Some(v.len() as u64 + 1));
            }
            for (c, &us) in v.iter().enumerate() {
                // What the receiver read is what the log says, to its
                // capture's truncation.
                prop_assert!(
                    (us as f64 - logged[c]).abs() <= 1.0,
                    "{:?} read {:?}, logged {}",
                    r,
                    v,
                    row
                );
                if row["glitched"] == false {
                    // And, unless an edge was held up in its write,
                    // a value commanded, within the guard.
                    prop_assert!(
                        allowed[c].iter().any(|&a| a.abs_diff(us) <= guard_us + 1),
                        "{:?} read {} us on channel {} of {}",
                        r,
                        us,
                        c,
                        row
                    );
                }
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(
        std::env::var("PROPTEST_CASES").map_or(64, |c| c.parse().expect("a number")),
    ))]

    /// Stalls of any length at any point of any frame, and writes held
    /// up (on a real line, where that can delay the edge, and on a
    /// stamped one, where it cannot), in either timing, with 5..=12 channels and either idle level:
    /// every modelled receiver, decoding the times the edges reached
    /// the line, reads only commanded values (within the guard) from
    /// every frame the log does not call glitched; reads a short frame
    /// only where the log has an aborted one, cut at the channel it
    /// says; and reads the values the log has, to its capture's
    /// truncation. The counters match the log.
    #[test]
    fn late_edges_never_become_wrong_values_and_the_log_says_what_the_line_carried(
        stamped in any::<bool>(),
        follow in any::<bool>(),
        idle_high in any::<bool>(),
        channels in 5usize..=12,
        cmds in prop::collection::vec((1u64..60, any::<u64>()), 1..25),
        stalls in prop::collection::vec((0u64..600, 1u64..40_000), 0..5),
        held in prop::collection::vec((0usize..1_500, 1u64..5_000), 0..3),
        late_us in 0u64..80,
        action in any_action(),
    ) {
        check_late_edges((stamped, follow, idle_high, channels, cmds, stalls, held, late_us, action))?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Two grid outputs of one loop, as the two-output whole-system test
    /// runs them (8 channels at 22.5 ms, 6 at 20 ms, the 20 us guard,
    /// commands always fresh), with readings of the clock as slow as in a
    /// debug build and sleeps that wake a little late: a frame is aborted
    /// only where the loop was held up (a stall), never by the other
    /// output's edges or decisions, and one stall costs each output at
    /// most one frame.
    #[test]
    fn two_outputs_lose_frames_only_to_stalls(
        read_ns in 100u64..3_000,
        late_us in 0u64..300,
        stalls in prop::collection::vec((0u64..1_500, 30u64..3_000), 0..4),
        start_ms in 0u64..40,
    ) {
        let guard = "late_edge_guard_us = 20\n";
        let a = timed_model(false, guard);
        let b = timed_model(false, &format!("{SIX_AT_20_MS}\n{guard}"));
        let sim = scenario_sim(&stalls, late_us);
        sim.set_read_ns(read_ns);
        let mut src_a = Fresh::new(&sim, &a, CMD);
        let mut src_b = Fresh::new(&sim, &b, "[1900, 1800, 1700, 1600, 1500, 1000]");
        // b's frames start at any phase against a's.
        sim.stall_at(START_NS, start_ms * MS);
        let (mut out_a, mut out_b) = (Recorder::default(), Recorder::default());
        let silence = scenario_cfg(FailsafeAction::Silence);
        let (stats_a, stats_b) = run_two(
            &sim,
            (&a, silence, &mut src_a, LineRef::Edges(&mut out_a)),
            (&b, silence, &mut src_b, LineRef::Edges(&mut out_b)),
            1_600,
        );
        for (name, stats) in [("a", &stats_a), ("b", &stats_b)] {
            let aborted = stats.aborted_frames.load(Relaxed);
            prop_assert!(
                aborted <= stalls.len() as u64,
                "{}: {} aborted frames of {}, {} stalls: {:?}",
                name, aborted, stats.frames.load(Relaxed), stalls.len(), stats
            );
        }
    }
}

/// A source that holds the loop up `slow_ns` in its first look (as a
/// subscriber's first receive from a new publisher maps its memory).
struct SlowFirst {
    inner: Fresh,
    slow_ns: u64,
}

impl CommandSource for SlowFirst {
    fn newest(&mut self) -> Option<CommandSample> {
        self.inner.sim.advance(std::mem::take(&mut self.slow_ns));
        self.inner.newest()
    }
}

/// Two grid outputs of one loop (as [`two_outputs_lose_frames_only_to_stalls`]
/// runs them), one of whose sources holds the loop up in its first look, 1
/// to 10 ms (as a subscriber's first receive from a publisher that just
/// came maps its memory): no frame after it is moved late or aborted, and
/// both lines carry as many frames as without the hold, but for the one
/// it falls on. (The slot kept
/// free for a decision followed the longest decision seen, decaying by
/// 1/64 a decision: after one 3 ms decision it kept deferring decisions
/// until a gap that long, and moved 11 of a's 71 frames late and 29 of
/// b's 80.)
#[test]
fn a_decision_held_up_once_moves_no_later_frame() {
    let guard = "late_edge_guard_us = 20\n";
    let a = timed_model(false, guard);
    let b = timed_model(false, &format!("{SIX_AT_20_MS}\n{guard}"));
    let run = |slow_us: u64, start_ms: u64| {
        let sim = scenario_sim(&[], 5);
        sim.set_read_ns(1_000);
        let mut src_a = SlowFirst {
            inner: Fresh::new(&sim, &a, CMD),
            slow_ns: slow_us * 1_000,
        };
        let mut src_b = Fresh::new(&sim, &b, "[1900, 1800, 1700, 1600, 1500, 1000]");
        sim.stall_at(START_NS, start_ms * MS);
        let (mut out_a, mut out_b) = (Recorder::default(), Recorder::default());
        let silence = scenario_cfg(FailsafeAction::Silence);
        run_two(
            &sim,
            (&a, silence, &mut src_a, LineRef::Edges(&mut out_a)),
            (&b, silence, &mut src_b, LineRef::Edges(&mut out_b)),
            1_600,
        )
    };
    for start_ms in [0, 7] {
        let (base_a, base_b) = run(0, start_ms);
        for slow_us in [1_000, 3_000, 10_000] {
            let (stats_a, stats_b) = run(slow_us, start_ms);
            for (stats, base) in [(&stats_a, &base_a), (&stats_b, &base_b)] {
                let what = format!("held {slow_us} us, b from {start_ms} ms: {stats:?}");
                assert_eq!(stats.late_frames.load(Relaxed), 0, "{what}");
                assert_eq!(stats.aborted_frames.load(Relaxed), 0, "{what}");
                // The hold may cost the one frame it falls on.
                let (got, base) = (stats.frames.load(Relaxed), base.frames.load(Relaxed));
                assert!(got + 1 >= base, "{got} frames of {base}: {what}");
            }
        }
    }
}
