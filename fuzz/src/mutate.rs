//! The mutator: seeded, byte-level and token-aware. Each new input is a pool entry with one
//! to four stacked edits: bit flips, interesting bytes, deletions, insertions, duplicated
//! chunks, dictionary tokens, numbers replaced by boundary values (NaN, ∞, 2³², −1, …),
//! quoted strings replaced by path-like or empty strings, and splices of two entries.

/// SplitMix64: a small, fast, seeded generator (the campaign is reproducible from its seed).
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// A generator from `seed`.
    pub fn new(seed: u64) -> Rng {
        Rng(seed)
    }

    /// The next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// A uniform index below `n` (0 when `n` is 0).
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next_u64() % n as u64) as usize
        }
    }
}

/// Numbers that break unchecked code: non-finite, negative, zero, beyond 32 and 64 bits,
/// just past hexcal's limits, tiny.
const NUMBERS: &[&str] = &[
    "0",
    "-1",
    "1",
    "nan",
    "inf",
    "-inf",
    "NaN",
    "1e308",
    "-1e308",
    "1e-300",
    "0.001",
    "2147483648",
    "-2147483649",
    "4294967295",
    "4294967296",
    "18446744073709551615",
    "18446744073709551616",
    "65536",
    "65537",
    "268435457",
    "10001",
    "100001",
    "1000000000",
    "3",
    "12",
    "255",
];

/// Strings that break unchecked names and paths.
const STRINGS: &[&str] = &[
    "",
    "..",
    "../../etc/passwd",
    "/etc/passwd",
    "a/b",
    ".",
    "cam0",
    "proj0",
    "hex600",
    "front",
    "back",
    "unanchored",
    "camera",
    "projector",
];

/// Bytes worth setting.
const BYTES: &[u8] = b"\x00\x01\x7f\x80\xff09-.\"[]{},:=\n#e";

/// Longest input the mutator makes.
pub const MAX_LEN: usize = 64 << 10;

/// The tokens of `text` worth inserting elsewhere: identifiers, quoted strings, numbers,
/// table headers and punctuation runs of the seeds.
pub fn dictionary(seeds: &[Vec<u8>]) -> Vec<Vec<u8>> {
    let mut out: Vec<Vec<u8>> = NUMBERS.iter().map(|s| s.as_bytes().to_vec()).collect();
    for seed in seeds {
        let mut start = None;
        for (i, b) in seed.iter().copied().enumerate().chain([(seed.len(), b' ')]) {
            let word = b.is_ascii_alphanumeric() || b"_.-\"[]".contains(&b);
            match (word, start) {
                (true, None) => start = Some(i),
                (false, Some(s)) => {
                    if i - s <= 40 {
                        out.push(seed[s..i].to_vec());
                    }
                    start = None;
                }
                _ => {}
            }
        }
    }
    out.sort();
    out.dedup();
    out
}

/// A mutation of `pool[pick]`: one to four stacked edits, at most [`MAX_LEN`] bytes.
pub fn mutate(pool: &[Vec<u8>], dict: &[Vec<u8>], rng: &mut Rng) -> Vec<u8> {
    let mut data = pool[rng.below(pool.len())].clone();
    for _ in 0..1 + rng.below(4) {
        edit(&mut data, pool, dict, rng);
    }
    data.truncate(MAX_LEN);
    data
}

/// One edit of `data`.
fn edit(data: &mut Vec<u8>, pool: &[Vec<u8>], dict: &[Vec<u8>], rng: &mut Rng) {
    let len = data.len();
    let at = rng.below(len + 1);
    match rng.below(9) {
        0 if len > 0 => data[at.min(len - 1)] ^= 1 << rng.below(8),
        1 if len > 0 => data[at.min(len - 1)] = BYTES[rng.below(BYTES.len())],
        2 if len > 0 => {
            let n = (1 + rng.below(16)).min(len - at.min(len - 1));
            data.drain(at.min(len - 1)..at.min(len - 1) + n);
        }
        3 => {
            let bytes: Vec<u8> = (0..1 + rng.below(8))
                .map(|_| rng.next_u64() as u8)
                .collect();
            data.splice(at..at, bytes);
        }
        4 if len > 0 => {
            let from = rng.below(len);
            let n = (1 + rng.below(64)).min(len - from);
            let chunk = data[from..from + n].to_vec();
            data.splice(at..at, chunk);
        }
        5 if !dict.is_empty() => {
            let token = dict[rng.below(dict.len())].clone();
            data.splice(at..at, token);
        }
        6 => replace_number(data, rng),
        7 => replace_string(data, rng),
        _ => {
            let other = &pool[rng.below(pool.len())];
            let cut = rng.below(other.len() + 1);
            data.truncate(at);
            data.extend_from_slice(&other[cut..]);
        }
    }
}

/// Replaces a number of `data` (a run of digits with its sign, point and exponent) by one
/// of [`NUMBERS`].
fn replace_number(data: &mut Vec<u8>, rng: &mut Rng) {
    let starts: Vec<usize> = (0..data.len())
        .filter(|&i| data[i].is_ascii_digit() && (i == 0 || !data[i - 1].is_ascii_digit()))
        .collect();
    if starts.is_empty() {
        return;
    }
    let mut s = starts[rng.below(starts.len())];
    if s > 0 && data[s - 1] == b'-' {
        s -= 1;
    }
    let mut e = s + 1;
    while e < data.len() && (data[e].is_ascii_digit() || b".eE+-".contains(&data[e])) {
        e += 1;
    }
    let number = NUMBERS[rng.below(NUMBERS.len())].as_bytes().to_vec();
    data.splice(s..e, number);
}

/// Replaces the content of a quoted string of `data` by one of [`STRINGS`], or a copy of
/// another string of the input (a duplicate name).
fn replace_string(data: &mut Vec<u8>, rng: &mut Rng) {
    let quotes: Vec<usize> = (0..data.len()).filter(|&i| data[i] == b'"').collect();
    if quotes.len() < 2 {
        return;
    }
    let pair = rng.below(quotes.len() / 2);
    let (s, e) = (quotes[2 * pair] + 1, quotes[2 * pair + 1]);
    let with = if rng.below(3) == 0 {
        let other = rng.below(quotes.len() / 2);
        data[quotes[2 * other] + 1..quotes[2 * other + 1]].to_vec()
    } else {
        STRINGS[rng.below(STRINGS.len())].as_bytes().to_vec()
    };
    data.splice(s..e, with);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutation_is_seeded_and_bounded() {
        let pool = vec![b"width = 1920\nname = \"cam0\"\n".to_vec(), b"{}".to_vec()];
        let dict = dictionary(&pool);
        assert!(dict.contains(&b"width".to_vec()) && dict.contains(&b"nan".to_vec()));
        let run = |seed| {
            let mut rng = Rng::new(seed);
            (0..2000)
                .map(|_| mutate(&pool, &dict, &mut rng))
                .collect::<Vec<_>>()
        };
        let a = run(7);
        assert_eq!(a, run(7), "same seed, same inputs");
        assert_ne!(a, run(8));
        assert!(a.iter().all(|m| m.len() <= MAX_LEN));
        assert!(a.iter().any(|m| m.windows(3).any(|w| w == b"nan")));
        assert!(a.iter().any(|m| m.windows(2).any(|w| w == b"..")));
    }
}
