//! Output stage: the human summary, the JSON summary (contract section 5), the ROS messages of
//! contract section 2 and the output bag.

pub mod bag;
pub mod json;
pub mod messages;
pub mod table;

pub use bag::BagWriter;
