//! Frame packing on a CAN FD bus: several messages a node sends at one instant travel as one container frame
//! (AUTOSAR's static container PDU), and every receiver gets them back as the messages they were.
//!
//! A container has a frame ID of its own and carries its parts at fixed byte offsets, each part a whole message
//! with its own E2E header (the DBC says where: `dbc/train_fd.dbc`). A sender's batch that holds every part of a
//! container exactly once goes as that container, placed where its first part was; any other batch (a part
//! missing, say an ECU with a stale sensor that sends only its command) goes frame by frame as before. A receiver
//! accepts a container when it accepts any of its parts, and takes the parts it accepts; a part that does not lie
//! within the frame's data is left out. Unpacked frames never change: a bus without packing runs as before.

use std::collections::HashMap;

use crate::bus::Payload;
use crate::frame::{fd_padded_len, MAX_DATA};

/// One message inside a container: its frame ID, where its bytes start and how many there are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Part {
    pub id: u32,
    pub offset: usize,
    pub len: usize,
}

/// A container frame: its ID, its data length (a CAN FD length) and its parts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Container {
    pub id: u32,
    pub len: usize,
    pub parts: Vec<Part>,
}

/// The containers of one bus, looked up by container ID and by part ID.
#[derive(Debug, Clone, Default)]
pub struct Packing {
    containers: Vec<Container>,
    by_id: HashMap<u32, usize>,
    by_part: HashMap<u32, (usize, usize)>,
}

impl Packing {
    /// Check and index the containers: each is a CAN FD length that holds its parts without overlap, and no ID is
    /// two things (a container and a part, or a part of two containers).
    pub fn new(containers: Vec<Container>) -> Result<Packing, String> {
        let mut p = Packing::default();
        for (c, cont) in containers.iter().enumerate() {
            check(cont)?;
            if p.by_id.insert(cont.id, c).is_some() {
                return Err(format!("container {:#x} is defined twice", cont.id));
            }
            for (k, part) in cont.parts.iter().enumerate() {
                if p.by_part.insert(part.id, (c, k)).is_some() {
                    return Err(format!("frame {:#x} is a part of two containers", part.id));
                }
            }
        }
        if let Some(id) = p.by_id.keys().find(|id| p.by_part.contains_key(id)) {
            return Err(format!("frame {id:#x} is both a container and a part"));
        }
        p.containers = containers;
        Ok(p)
    }

    /// The parts of container `id` (None: `id` is not a container).
    pub fn parts(&self, id: u32) -> Option<&[Part]> {
        self.by_id.get(&id).map(|&c| self.containers[c].parts.as_slice())
    }

    /// True when `id` is a container or a part (a node accepting it may see container frames).
    pub fn involves(&self, id: u32) -> bool {
        self.by_id.contains_key(&id) || self.by_part.contains_key(&id)
    }

    /// The containers that carry any of `ids` (what a node accepting `ids` must also accept).
    pub fn containers_of(&self, ids: &[u32]) -> Vec<u32> {
        let mut out: Vec<u32> = self.containers.iter()
            .filter(|c| c.parts.iter().any(|p| ids.contains(&p.id)))
            .map(|c| c.id)
            .collect();
        out.sort_unstable();
        out
    }

    /// A sender's batch as it goes on the bus: every container whose parts are all in the batch, once each and
    /// with the right lengths, replaces them (at its first part's place); the other frames stay as they are.
    pub fn pack(&self, frames: &[(u32, &[u8])]) -> Vec<(u32, Payload)> {
        let mut seen: HashMap<usize, Vec<Option<usize>>> = HashMap::new(); // container -> frame index per part
        let mut spoiled: Vec<usize> = Vec::new();
        for (i, (id, data)) in frames.iter().enumerate() {
            let Some(&(c, k)) = self.by_part.get(id) else { continue };
            let slots = seen.entry(c).or_insert_with(|| vec![None; self.containers[c].parts.len()]);
            if slots[k].is_some() || data.len() != self.containers[c].parts[k].len {
                spoiled.push(c);
            }
            slots[k] = Some(i);
        }
        let complete: HashMap<usize, usize> = seen.iter() // container -> its first frame index
            .filter(|(c, slots)| !spoiled.contains(c) && slots.iter().all(Option::is_some))
            .map(|(&c, slots)| (c, slots.iter().flatten().copied().min().unwrap_or(0)))
            .collect();
        let mut out = Vec::with_capacity(frames.len());
        for (i, (id, data)) in frames.iter().enumerate() {
            match self.by_part.get(id).map(|&(c, _)| c).filter(|c| complete.contains_key(c)) {
                Some(c) if complete[&c] == i => out.push(self.fill(c, frames, &seen[&c])),
                Some(_) => {}
                None => out.push((*id, Payload::new(data))),
            }
        }
        out
    }

    fn fill(&self, c: usize, frames: &[(u32, &[u8])], slots: &[Option<usize>]) -> (u32, Payload) {
        let cont = &self.containers[c];
        let mut bytes = [0u8; MAX_DATA];
        for (part, slot) in cont.parts.iter().zip(slots) {
            let data = frames[slot.expect("a complete container")].1;
            bytes[part.offset..part.offset + part.len].copy_from_slice(data);
        }
        (cont.id, Payload::new(&bytes[..cont.len]))
    }

    /// The parts a container frame carries, as (part ID, its bytes); None when `id` is not a container. Parts that
    /// do not lie within `data` are left out.
    pub fn unpack<'a>(&'a self, id: u32, data: &'a [u8]) -> Option<impl Iterator<Item = (u32, &'a [u8])> + 'a> {
        let parts = self.parts(id)?;
        Some(parts.iter().filter(move |p| p.offset + p.len <= data.len()).map(move |p| (p.id, &data[p.offset..p.offset + p.len])))
    }
}

fn check(c: &Container) -> Result<(), String> {
    if fd_padded_len(c.len) != Some(c.len) {
        return Err(format!("container {:#x}: length {} is not a CAN FD length", c.id, c.len));
    }
    if c.parts.is_empty() {
        return Err(format!("container {:#x} has no parts", c.id));
    }
    let mut spans: Vec<(usize, usize)> = c.parts.iter().map(|p| (p.offset, p.offset + p.len)).collect();
    spans.sort_unstable();
    for (k, &(start, end)) in spans.iter().enumerate() {
        if end > c.len || end == start {
            return Err(format!("container {:#x}: a part at bytes {start}..{end} does not fit its {} bytes", c.id, c.len));
        }
        if k > 0 && start < spans[k - 1].1 {
            return Err(format!("container {:#x}: parts overlap at byte {start}", c.id));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_container() -> Packing {
        Packing::new(vec![Container { id: 0x70, len: 20, parts: vec![
            Part { id: 0x80, offset: 0, len: 5 }, Part { id: 0x100, offset: 5, len: 8 }, Part { id: 0x120, offset: 13, len: 7 }] }]).unwrap()
    }

    #[test]
    fn a_complete_batch_goes_as_one_container_and_comes_back_as_its_parts() {
        let p = unit_container();
        let (cmd, state, aux, other) = ([1u8; 5], [2u8; 8], [3u8; 7], [9u8; 8]);
        let out = p.pack(&[(0x200, &other), (0x80, &cmd), (0x100, &state), (0x120, &aux)]);
        assert_eq!(out.iter().map(|f| f.0).collect::<Vec<_>>(), vec![0x200, 0x70]);
        let frame = out[1].1;
        assert_eq!(frame.as_slice().len(), 20);
        let parts: Vec<(u32, Vec<u8>)> = p.unpack(0x70, frame.as_slice()).unwrap().map(|(i, d)| (i, d.to_vec())).collect();
        assert_eq!(parts, vec![(0x80, cmd.to_vec()), (0x100, state.to_vec()), (0x120, aux.to_vec())]);
        assert!(p.unpack(0x200, &other).is_none());
    }

    #[test]
    fn an_incomplete_or_odd_batch_goes_frame_by_frame() {
        let p = unit_container();
        let only_cmd = p.pack(&[(0x80, &[1u8; 5])]);
        assert_eq!(only_cmd.iter().map(|f| (f.0, f.1.len)).collect::<Vec<_>>(), vec![(0x80, 5)]);
        let wrong_len = p.pack(&[(0x80, &[1u8; 4]), (0x100, &[2u8; 8]), (0x120, &[3u8; 7])]);
        assert_eq!(wrong_len.len(), 3);
        let twice = p.pack(&[(0x80, &[1u8; 5]), (0x80, &[1u8; 5]), (0x100, &[2u8; 8]), (0x120, &[3u8; 7])]);
        assert_eq!(twice.len(), 4);
    }

    #[test]
    fn a_short_container_frame_yields_only_the_parts_within_it() {
        let p = unit_container();
        let got: Vec<u32> = p.unpack(0x70, &[0u8; 16]).unwrap().map(|(i, _)| i).collect();
        assert_eq!(got, vec![0x80, 0x100]);
        assert_eq!(p.containers_of(&[0x100, 0x999]), vec![0x70]);
        assert!(p.involves(0x70) && p.involves(0x120) && !p.involves(0x200));
    }

    #[test]
    fn bad_containers_are_refused() {
        let part = |id, offset, len| Part { id, offset, len };
        assert!(Packing::new(vec![Container { id: 1, len: 10, parts: vec![part(2, 0, 8)] }]).is_err()); // not an FD length
        assert!(Packing::new(vec![Container { id: 1, len: 12, parts: vec![part(2, 0, 8), part(3, 6, 4)] }]).is_err());
        assert!(Packing::new(vec![Container { id: 1, len: 12, parts: vec![part(2, 8, 8)] }]).is_err());
        assert!(Packing::new(vec![Container { id: 1, len: 8, parts: vec![part(1, 0, 8)] }]).is_err());
        assert!(Packing::new(vec![Container { id: 1, len: 8, parts: vec![part(2, 0, 8)] },
                                  Container { id: 3, len: 8, parts: vec![part(2, 0, 8)] }]).is_err());
    }
}
