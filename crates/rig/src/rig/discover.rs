//! What devices this machine has (`hexcal devices`): serial ports (trigger controllers),
//! video nodes, and — with the drivers' cargo features — GenICam cameras and monitors.

/// One device found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Found {
    /// Kind: "serial", "v4l2", "aravis" or "monitor".
    pub kind: &'static str,
    /// Address to put in a rig file (port path, device node, camera id, monitor name).
    pub address: String,
    /// What it says it is.
    pub description: String,
}

/// The system could not list its serial ports.
#[derive(Debug, thiserror::Error)]
#[error("serial ports: {0}")]
pub struct PortsError(#[from] pub serialport::Error);

/// Serial ports, as a rig file's `[trigger] port`.
pub fn serial_ports() -> Result<Vec<Found>, PortsError> {
    let ports = serialport::available_ports()?;
    Ok(ports
        .into_iter()
        .map(|p| Found {
            kind: "serial",
            description: match &p.port_type {
                serialport::SerialPortType::UsbPort(u) => format!(
                    "USB {:04x}:{:04x} {} {}",
                    u.vid,
                    u.pid,
                    u.manufacturer.as_deref().unwrap_or(""),
                    u.product.as_deref().unwrap_or("")
                )
                .trim_end()
                .to_string(),
                serialport::SerialPortType::PciPort => "PCI".into(),
                serialport::SerialPortType::BluetoothPort => "Bluetooth".into(),
                serialport::SerialPortType::Unknown => "serial".into(),
            },
            address: p.port_name,
        })
        .collect())
}

/// Video4Linux nodes (`/dev/video*`) with the name the kernel gives them; with the `v4l2`
/// feature, the card, driver and capture formats of each node that opens.
pub fn video_nodes() -> Vec<Found> {
    let mut found: Vec<Found> = std::fs::read_dir("/sys/class/video4linux")
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| {
            let node = e.file_name().to_string_lossy().into_owned();
            let address = format!("/dev/{node}");
            let name = std::fs::read_to_string(e.path().join("name")).unwrap_or_default();
            #[cfg(feature = "v4l2")]
            let name = crate::rig::v4l2::Node::open(&address)
                .and_then(|n| crate::rig::v4l2::describe(&n))
                .unwrap_or(name);
            Found {
                kind: "v4l2",
                address,
                description: name.trim().to_string(),
            }
        })
        .collect();
    found.sort_by(|a, b| a.address.cmp(&b.address));
    found
}
