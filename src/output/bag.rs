//! Writing ROS 2 MCAP bags as rosbag2 does: `ros2msg` schemas (with every nested definition),
//! `cdr` message encoding, zstd-compressed chunks.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use serde::Serialize;

use crate::msgs::{encode_cdr, ros2msg_schema};

/// Why a bag could not be written.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    #[error("{0}")]
    Io(#[from] std::io::Error),
    #[error("{0}")]
    Mcap(#[from] mcap::McapError),
    #[error("no message definition for {0}")]
    UnknownType(String),
    #[error("CDR encoding: {0}")]
    Cdr(#[from] crate::msgs::CdrError),
}

/// A ROS 2 MCAP writer.
pub struct BagWriter {
    writer: mcap::Writer<BufWriter<File>>,
    channels: HashMap<String, u16>,
    sequence: u32,
}

impl BagWriter {
    /// Create (or overwrite) `path`.
    pub fn create(path: &Path) -> Result<Self, WriteError> {
        let file = BufWriter::new(File::create(path)?);
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("bom ", env!("CARGO_PKG_VERSION")))
            .compression(Some(mcap::Compression::Zstd))
            // Small chunks: a bag cut short (a crash while recording) loses at most one chunk.
            .chunk_size(Some(64 * 1024))
            .create(file)?;
        Ok(BagWriter { writer, channels: HashMap::new(), sequence: 0 })
    }

    /// Write one message on `topic` of ROS type `type_name` (e.g. `sensor_msgs/msg/PointCloud2`)
    /// with log time `stamp_ns`.
    pub fn write<T: Serialize>(&mut self, topic: &str, type_name: &str, stamp_ns: u64, msg: &T) -> Result<(), WriteError> {
        let channel = match self.channels.get(topic) {
            Some(c) => *c,
            None => {
                let schema = ros2msg_schema(type_name).ok_or_else(|| WriteError::UnknownType(type_name.into()))?;
                let sid = self.writer.add_schema(type_name, "ros2msg", schema.as_bytes())?;
                let c = self.writer.add_channel(sid, topic, "cdr", &BTreeMap::new())?;
                self.channels.insert(topic.into(), c);
                c
            }
        };
        self.sequence += 1;
        let header = mcap::records::MessageHeader { channel_id: channel, sequence: self.sequence, log_time: stamp_ns, publish_time: stamp_ns };
        self.writer.write_to_known_channel(&header, &encode_cdr(msg)?)?;
        Ok(())
    }

    /// Write a metadata record (e.g. `bom_ground_truth` with key `json`).
    pub fn metadata(&mut self, name: &str, entries: BTreeMap<String, String>) -> Result<(), WriteError> {
        self.writer.write_metadata(&mcap::records::Metadata { name: name.into(), metadata: entries })?;
        Ok(())
    }

    /// Write the summary section and close the file.
    pub fn finish(mut self) -> Result<(), WriteError> {
        self.writer.finish()?;
        Ok(())
    }
}
