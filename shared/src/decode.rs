//! A PPM decoder with transmitter semantics (EdgeTX/OpenTX trainer input).
//!
//! It looks only at the periods between edges of one direction (the edges
//! that start a pulse): a period in the sync range ends a frame and starts the
//! next; a period in the channel range, once synchronised, is the next
//! channel; anything else loses synchronisation until the next sync. Pulse
//! width and polarity do not matter beyond choosing which edges to time.

use crate::signal::{
    Level, CHANNEL_MAX_US, CHANNEL_MIN_US, MAX_CHANNELS, SYNC_MAX_US, SYNC_MIN_US,
};

/// The ranges the decoder accepts, in nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DecoderLimits {
    /// Shortest channel period.
    pub channel_min_ns: u64,
    /// Longest channel period.
    pub channel_max_ns: u64,
    /// Shortest sync period.
    pub sync_min_ns: u64,
    /// Longest sync period.
    pub sync_max_ns: u64,
    /// Most channels in one frame.
    pub max_channels: usize,
}

impl Default for DecoderLimits {
    /// EdgeTX's trainer input: channels 800..2200 us, sync 4..19 ms, 16 channels.
    fn default() -> Self {
        DecoderLimits {
            channel_min_ns: (CHANNEL_MIN_US * 1e3) as u64,
            channel_max_ns: (CHANNEL_MAX_US * 1e3) as u64,
            sync_min_ns: (SYNC_MIN_US * 1e3) as u64,
            sync_max_ns: (SYNC_MAX_US * 1e3) as u64,
            max_channels: MAX_CHANNELS,
        }
    }
}

/// One decoded frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DecodedFrame {
    /// Time of the leading edge that started the frame (the end of the sync), ns.
    pub start_ns: u64,
    /// Channel periods in nanoseconds, in order.
    pub channels_ns: Vec<u64>,
    /// True when a valid sync period closed the frame; false when it ended in
    /// an invalid period or at the end of the input (a transmitter would still
    /// have applied the channels it read).
    pub complete: bool,
}

impl DecodedFrame {
    /// Channel values rounded to whole microseconds, as a transmitter stores them.
    pub fn channels_us(&self) -> Vec<u64> {
        self.channels_ns
            .iter()
            .map(|&ns| (ns + 500) / 1_000)
            .collect()
    }
}

/// Counts of what the decoder threw away.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DecoderStats {
    /// Leading edges seen.
    pub edges: u64,
    /// Periods that were neither a channel nor a sync (or a channel before the first sync).
    pub invalid_periods: u64,
    /// Frames that had more than `max_channels` channels.
    pub overflows: u64,
}

/// Which level changes a PPM reader times: those to the `leading` level; a
/// repeated level is no edge.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LeadingEdges {
    leading: Level,
    level: Option<Level>,
}

impl LeadingEdges {
    pub(crate) fn new(leading: Level) -> LeadingEdges {
        LeadingEdges {
            leading,
            level: None,
        }
    }

    /// Notes the line's level after a change; true when it is a timed edge.
    pub(crate) fn timed(&mut self, level: Level) -> bool {
        let changed = self.level.replace(level) != Some(level);
        changed && level == self.leading
    }
}

/// Streaming decoder: feed edges in time order with [`Decoder::push`].
#[derive(Debug, Clone)]
pub struct Decoder {
    limits: DecoderLimits,
    edges: LeadingEdges,
    last_leading_ns: Option<u64>,
    frame: Option<DecodedFrame>,
    stats: DecoderStats,
}

impl Decoder {
    /// A decoder that times the edges after which the line is at `leading`
    /// (the active level, opposite to the idle level).
    pub fn new(leading: Level, limits: DecoderLimits) -> Decoder {
        Decoder {
            limits,
            edges: LeadingEdges::new(leading),
            last_leading_ns: None,
            frame: None,
            stats: DecoderStats::default(),
        }
    }

    /// What was discarded so far.
    pub fn stats(&self) -> DecoderStats {
        self.stats
    }

    /// Feeds the line's level after a change at `at_ns`. A repeated level is
    /// not an edge and is ignored. Returns a frame when this edge ended one.
    pub fn push(&mut self, at_ns: u64, level: Level) -> Option<DecodedFrame> {
        if !self.edges.timed(level) {
            return None;
        }
        self.stats.edges += 1;
        let prev = self.last_leading_ns.replace(at_ns)?;
        let period = at_ns.saturating_sub(prev);
        let l = &self.limits;
        if (l.sync_min_ns..=l.sync_max_ns).contains(&period) {
            let done = self.frame.take().map(|mut f| {
                f.complete = true;
                f
            });
            self.frame = Some(DecodedFrame {
                start_ns: at_ns,
                channels_ns: Vec::with_capacity(l.max_channels),
                complete: false,
            });
            return done.filter(|f| !f.channels_ns.is_empty());
        }
        if (l.channel_min_ns..=l.channel_max_ns).contains(&period) {
            if let Some(f) = &mut self.frame {
                if f.channels_ns.len() < l.max_channels {
                    f.channels_ns.push(period);
                    return None;
                }
                self.stats.overflows += 1;
                self.frame = None;
                return None;
            }
        }
        self.stats.invalid_periods += 1;
        self.frame.take().filter(|f| !f.channels_ns.is_empty())
    }

    /// Ends the input: returns the frame in progress, if it has channels.
    pub fn finish(&mut self) -> Option<DecodedFrame> {
        self.frame.take().filter(|f| !f.channels_ns.is_empty())
    }
}

/// Decodes a whole waveform given as `(time_ns, level_after)` changes.
pub fn decode(
    edges: impl IntoIterator<Item = (u64, Level)>,
    leading: Level,
    limits: DecoderLimits,
) -> Vec<DecodedFrame> {
    let mut d = Decoder::new(leading, limits);
    let mut frames: Vec<DecodedFrame> = edges
        .into_iter()
        .filter_map(|(t, l)| d.push(t, l))
        .collect();
    frames.extend(d.finish());
    frames
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pulses(starts: &[u64], width: u64) -> Vec<(u64, Level)> {
        starts
            .iter()
            .flat_map(|&t| [(t, Level::High), (t + width, Level::Low)])
            .collect()
    }

    #[test]
    fn needs_a_sync_before_channels() {
        // A pulse train with no sync period at the beginning: the first frame is
        // not decoded, as on a transmitter.
        let ms = 1_000_000;
        let starts = [
            0,
            ms,
            2 * ms,
            3 * ms,
            10 * ms,
            11 * ms,
            12 * ms,
            13 * ms,
            20 * ms,
        ];
        let f = decode(
            pulses(&starts, 300_000),
            Level::High,
            DecoderLimits::default(),
        );
        assert_eq!(f.len(), 1);
        assert_eq!(f[0].start_ns, 10 * ms);
        assert_eq!(f[0].channels_ns, [ms, ms, ms]);
        assert!(f[0].complete);
    }

    #[test]
    fn invalid_period_loses_sync() {
        let ms = 1_000_000;
        // sync, channel, 3 ms (invalid), channel, sync, channel, end.
        let starts = [0, 5 * ms, 6 * ms, 9 * ms, 10 * ms, 15 * ms, 16 * ms];
        let mut d = Decoder::new(Level::High, DecoderLimits::default());
        let mut out = vec![];
        for (t, l) in pulses(&starts, 300_000) {
            out.extend(d.push(t, l));
        }
        out.extend(d.finish());
        assert_eq!(out.len(), 2);
        assert_eq!(
            (out[0].channels_ns.clone(), out[0].complete),
            (vec![ms], false)
        );
        assert_eq!((out[1].start_ns, out[1].complete), (15 * ms, false));
        assert_eq!(
            d.stats().invalid_periods,
            2,
            "the 3 ms period and the channel after it"
        );
    }

    #[test]
    fn polarity_only_chooses_the_edges() {
        let ms = 1_000_000;
        let starts = [
            0,
            5 * ms,
            6 * ms,
            8 * ms,
            13 * ms,
            14 * ms,
            16 * ms,
            21 * ms,
        ];
        let inverted: Vec<_> = pulses(&starts, 400_000)
            .into_iter()
            .map(|(t, l)| (t, l.opposite()))
            .collect();
        let a = decode(
            pulses(&starts, 400_000),
            Level::High,
            DecoderLimits::default(),
        );
        let b = decode(inverted, Level::Low, DecoderLimits::default());
        assert_eq!(a, b);
        assert_eq!(a[0].channels_ns, [ms, 2 * ms]);
    }

    #[test]
    fn too_many_channels_overflow() {
        let ms = 1_000_000;
        let mut starts = vec![0u64, 5 * ms];
        for i in 1..=17 {
            starts.push(5 * ms + i * ms);
        }
        let mut d = Decoder::new(Level::High, DecoderLimits::default());
        let frames: Vec<_> = pulses(&starts, 300_000)
            .into_iter()
            .filter_map(|(t, l)| d.push(t, l))
            .collect();
        assert!(frames.is_empty());
        assert_eq!(d.stats().overflows, 1);
        assert_eq!(d.finish(), None);
    }
}
