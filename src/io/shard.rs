//! A stable partition of scenes into `n` shards by scenario id, for array jobs of an existing
//! scheduler (Slurm job arrays, Kubernetes Indexed Jobs): shard `i` of `n` takes the scenes
//! whose id hashes to `i`, whatever the order or the machine, so every scene is in exactly
//! one shard and a rerun of a shard takes the same scenes.

use std::fmt;
use std::str::FromStr;

/// Shard `index` of `count` (0 ≤ index < count).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    /// Which shard, from 0 (Slurm's `$SLURM_ARRAY_TASK_ID` with `--array=0-(n-1)`, a
    /// Kubernetes Indexed Job's `$JOB_COMPLETION_INDEX`).
    pub index: usize,
    /// How many shards.
    pub count: usize,
}

/// The most shards a run may be split into.
pub const MAX_SHARDS: usize = 1_000_000;

impl Shard {
    /// Whether the scene with this scenario id belongs to this shard.
    pub fn contains(&self, scenario_id: &str) -> bool {
        shard_of(scenario_id, self.count) == self.index
    }
}

/// The shard of `n` a scenario id falls in: CRC-32C of the id's bytes, modulo `n` (the same
/// on every platform and in every version that keeps this function).
pub fn shard_of(scenario_id: &str, n: usize) -> usize {
    super::tfrecord::crc32c(scenario_id.as_bytes()) as usize % n.max(1)
}

impl FromStr for Shard {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        // Without the value: clap quotes it, cut where it is long, before this message.
        let bad = || format!("a shard is I/N with 0 <= I < N <= {MAX_SHARDS}, e.g. 0/8");
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let (index, count): (usize, usize) = (
            i.trim().parse().map_err(|_| bad())?,
            n.trim().parse().map_err(|_| bad())?,
        );
        if count == 0 || count > MAX_SHARDS || index >= count {
            return Err(bad());
        }
        Ok(Self { index, count })
    }
}

impl fmt::Display for Shard {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_parse_with_their_range() {
        assert_eq!("2/8".parse::<Shard>(), Ok(Shard { index: 2, count: 8 }));
        for bad in ["8/8", "0/0", "1", "a/2", "-1/2", "0/2000000"] {
            assert!(bad.parse::<Shard>().is_err(), "{bad}");
        }
    }

    #[test]
    fn every_id_falls_in_exactly_one_shard_and_always_the_same() {
        // Known answers (CRC-32C 0x750d0d16, computed independently) keep the partition
        // stable across versions: a rerun of a shard takes the same scenes.
        assert_eq!(shard_of("USA_US101-3_3_T-1", 1000), 590);
        assert_eq!(shard_of("USA_US101-3_3_T-1", 7), 0);
        let ids: Vec<String> = (0..400).map(|k| format!("scene_{k}")).collect();
        let n = 5;
        let mut sizes = vec![0; n];
        for id in &ids {
            let hits: Vec<usize> = (0..n)
                .filter(|&i| Shard { index: i, count: n }.contains(id))
                .collect();
            assert_eq!(hits.len(), 1, "{id}");
            sizes[hits[0]] += 1;
        }
        // A hash, not a round-robin on order: still roughly even.
        assert!(sizes.iter().all(|&s| (50..=110).contains(&s)), "{sizes:?}");
    }
}
