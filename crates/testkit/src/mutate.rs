//! Seeded mutations of file bytes for the readers' fuzz tests (dataset's `tests/fuzz.rs`, encoder's
//! `tests/fuzz_ckpt.rs`): the same cases on every machine for one seed.

/// xorshift64*: the same cases on every machine.
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Values a crafted file puts where counts and sizes go.
pub const EXTREMES: [u64; 9] = [0, 1, u64::MAX, u64::MAX / 24, u64::MAX / 24 + 1, 1 << 31, (1 << 32) - 1, 0x7ff8_0000_0000_0000, 0xfff0_0000_0000_0000];

/// Byte flips, truncations, inserted bytes and 4- or 8-byte fields overwritten with extreme values (half the
/// time where the original holds a small positive integer: a count or a size).
pub fn mutate_binary(rng: &mut Rng, data: &[u8]) -> Vec<u8> {
    let mut d = data.to_vec();
    for _ in 0..1 + rng.below(3) {
        match rng.below(5) {
            0 if !d.is_empty() => {
                let i = rng.below(d.len());
                d[i] ^= 1 << rng.below(8);
            }
            1 => d.truncate(rng.below(d.len() + 1)),
            2 => {
                let i = rng.below(d.len() + 1);
                let extra: Vec<u8> = (0..1 + rng.below(16)).map(|_| rng.next() as u8).collect();
                d.splice(i..i, extra);
            }
            _ if d.len() >= 8 => {
                // A count, id, size or parameter field: 4 or 8 bytes, half the time where the original holds a
                // small positive integer (a count or a size, what a crafted file would change).
                let counts: Vec<usize> = (0..d.len() - 7)
                    .filter(|&i| (1..100_000).contains(&u64::from_le_bytes(data.get(i..i + 8).and_then(|b| b.try_into().ok()).unwrap_or([0; 8]))))
                    .collect();
                let i = if !counts.is_empty() && rng.below(2) == 0 { counts[rng.below(counts.len())] } else { rng.below(d.len() - 7) };
                let v = EXTREMES[rng.below(EXTREMES.len())];
                let w = if rng.below(2) == 0 { 8 } else { 4 };
                d[i..i + w].copy_from_slice(&v.to_le_bytes()[..w]);
            }
            _ => d.clear(),
        }
    }
    d
}

/// A zip archive (a `.torch` chunk, a Lightning `.ckpt`) with one entry mutated ([`mutate_binary`]) and the archive
/// written again, so that the mutation reaches the unpickler and the tensor readers, not only the zip's checksums:
/// the entry ending in `prefer` (the pickle) half the time, else any.
pub fn mutate_zip_entry(rng: &mut Rng, data: &[u8], prefer: &str) -> Vec<u8> {
    use std::io::{Read, Write};
    let mut zin = zip::ZipArchive::new(std::io::Cursor::new(data)).unwrap();
    let names: Vec<String> = zin.file_names().map(|n| n.unwrap().into_owned()).collect();
    let pkl = names.iter().position(|n| n.ends_with(prefer)).unwrap_or(0);
    let pick = if rng.below(2) == 0 { pkl } else { rng.below(names.len()) };
    let mut out = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (k, name) in names.iter().enumerate() {
        let mut bytes = Vec::new();
        zin.by_name(name).unwrap().read_to_end(&mut bytes).unwrap();
        if k == pick {
            bytes = mutate_binary(rng, &bytes);
        }
        out.start_file(name.clone(), opts).unwrap();
        out.write_all(&bytes).unwrap();
    }
    out.finish().unwrap().into_inner()
}
