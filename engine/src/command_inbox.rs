//! A real-time plant's command inbox: its TractionCmd frames checked and decoded on receipt, as the virtual network's
//! command node does on delivery, and the sensor-to-actuator latency closed by its AgentState frames, so that no
//! frame the plant receives is handed to Python one by one.
//!
//! The latency of unit u: when u's AgentState numbered with Sensor sample k arrives, the arrival time of u's last
//! valid TractionCmd (length, E2E CRC, mode) minus the publication time of sample k. The ECU sends both in one cycle,
//! the command first (lower ID), so this is "sensor sampled -> command at the plant".

use std::collections::HashMap;

use crate::bus::Payload;
use crate::network::{Command, CommandTable};

/// Alive counters a Sensor sample can carry (E2E counters are 4 bits).
const COUNTERS: usize = 16;

/// See the module documentation. Times are simulated seconds.
pub struct CommandInbox {
    table: CommandTable,
    /// AgentState frame ID -> unit: the frames that close a latency.
    states: HashMap<u32, usize>,
    /// Publication time of each unit's Sensor sample, by alive counter (-inf: none yet).
    published: Vec<[f64; COUNTERS]>,
    /// Arrival time of each unit's last valid command (-inf: none yet).
    last_command: Vec<f64>,
    /// Valid commands in arrival order.
    pub commands: Vec<Command>,
    /// Frames of the table's IDs refused (length, CRC, mode), in arrival order: (frame id, payload, arrival s).
    pub rejected: Vec<(u32, Payload, f64)>,
    /// (command arrival, latency) of every AgentState that closed one, in arrival order.
    pub latencies: Vec<(f64, f64)>,
    scratch: Vec<f64>,
}

/// A unit out of an inbox's range.
#[derive(Debug, PartialEq)]
pub struct NoSuchUnit(pub usize);

impl CommandInbox {
    /// An inbox for `units` units: `table`'s commands, `states` (AgentState frame ID -> unit) for the latency.
    pub fn new(table: CommandTable, states: HashMap<u32, usize>, units: usize) -> Result<Self, NoSuchUnit> {
        let too_high = table.by_id.values().map(|(u, _)| *u).chain(states.values().copied()).find(|&u| u >= units);
        if let Some(u) = too_high {
            return Err(NoSuchUnit(u));
        }
        Ok(CommandInbox { table, states, published: vec![[f64::NEG_INFINITY; COUNTERS]; units],
                          last_command: vec![f64::NEG_INFINITY; units], commands: Vec::new(), rejected: Vec::new(),
                          latencies: Vec::new(), scratch: Vec::with_capacity(2) })
    }

    /// The frame IDs it takes: its commands' and its AgentStates'.
    pub fn ids(&self) -> Vec<u32> {
        self.table.by_id.keys().chain(self.states.keys()).copied().collect()
    }

    /// A frame received at `t`: a command is queued (or refused), an AgentState closes a latency. Whether the frame
    /// was one of its IDs.
    pub fn put(&mut self, frame_id: u32, data: &[u8], t: f64) -> bool {
        if self.table.by_id.contains_key(&frame_id) {
            match self.table.check(frame_id, data, &mut self.scratch) {
                Some((unit, force, mode, counter)) => {
                    self.commands.push((unit, force, mode, t, counter));
                    self.last_command[unit] = t;
                }
                None => self.rejected.push((frame_id, Payload::new(data), t)),
            }
            return true;
        }
        let Some(&unit) = self.states.get(&frame_id) else { return false };
        if let Some(&byte) = data.get(1) {
            let (last, sampled) = (self.last_command[unit], self.published[unit][(byte & 0xF) as usize]);
            if last.is_finite() && last >= sampled {
                self.latencies.push((last, last - sampled));
            }
        }
        true
    }

    /// Unit `unit`'s Sensor sample with alive counter `counter` was published at `t`.
    pub fn published(&mut self, unit: usize, counter: u8, t: f64) -> Result<(), NoSuchUnit> {
        let samples = self.published.get_mut(unit).ok_or(NoSuchUnit(unit))?;
        samples[(counter & 0xF) as usize] = t;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::tests::{command_frame, command_table};

    const STATE: u32 = 0x100;

    fn inbox() -> CommandInbox {
        CommandInbox::new(command_table(), HashMap::from([(STATE, 3)]), 4).unwrap()
    }

    fn state(counter: u8) -> Vec<u8> {
        vec![0, counter, 0, 0, 0, 0, 0, 0]
    }

    #[test]
    fn valid_commands_are_queued_decoded_and_refused_ones_kept_raw_in_arrival_order() {
        let mut inbox = inbox();
        let table = command_table();
        let (good, mut corrupt) = (command_frame(&table, 1.0, -1200.0, 7), command_frame(&table, 0.0, 5.0, 8));
        corrupt[4] ^= 0x01;
        assert!(inbox.put(0x80, &good, 1.5));
        assert!(inbox.put(0x80, &corrupt, 1.6));
        assert!(!inbox.put(0x81, &good, 1.7), "not one of its IDs");
        assert_eq!(inbox.commands, vec![(3, -1200.0, 1, 1.5, 7)]);
        assert_eq!(inbox.rejected.len(), 1);
        assert_eq!((inbox.rejected[0].0, inbox.rejected[0].1.as_slice(), inbox.rejected[0].2), (0x80, &corrupt[..], 1.6));
        let mut ids = inbox.ids();
        ids.sort();
        assert_eq!(ids, vec![0x80, STATE]);
    }

    #[test]
    fn an_agent_state_closes_the_latency_from_its_sample_to_the_last_valid_command() {
        let mut inbox = inbox();
        let good = command_frame(&command_table(), 1.0, 0.0, 1);
        inbox.put(STATE, &state(5), 0.9);
        assert!(inbox.latencies.is_empty(), "no command yet");
        inbox.published(3, 5, 1.0).unwrap();
        inbox.put(0x80, &good, 1.0025);
        let mut corrupt = command_frame(&command_table(), 1.0, 0.0, 2);
        corrupt[4] ^= 0x01;
        inbox.put(0x80, &corrupt, 1.0027); // refused: not the command the latency ends at
        assert!(inbox.put(STATE, &state(5), 1.003));
        assert_eq!(inbox.latencies.len(), 1);
        let (t, latency) = inbox.latencies[0];
        assert_eq!(t, 1.0025);
        assert!((latency - 0.0025).abs() < 1e-12);
        inbox.published(3, 6, 1.01).unwrap();
        inbox.put(STATE, &state(6), 1.011);
        assert_eq!(inbox.latencies.len(), 1, "sample 6 came after the last command: no latency");
    }

    #[test]
    fn units_out_of_range_are_refused() {
        assert_eq!(CommandInbox::new(command_table(), HashMap::new(), 3).err(), Some(NoSuchUnit(3)));
        assert_eq!(CommandInbox::new(command_table(), HashMap::from([(STATE, 9)]), 4).err(), Some(NoSuchUnit(9)));
        assert_eq!(inbox().published(4, 0, 0.0), Err(NoSuchUnit(4)));
    }
}
