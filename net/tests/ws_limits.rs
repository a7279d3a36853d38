//! The stream client's WebSocket accepts a message as large as a protocol frame: a base mesh over
//! tungstenite's default 16 MiB must arrive whole. On loopback, bounded waits.

use futures_util::{SinkExt, StreamExt};
use std::time::Duration;
use tetwave_net::connection::ws_config;
use tetwave_protocol::wire::MAX_FRAME_BYTES;
use tokio_tungstenite::tungstenite::Message;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_message_over_16_mib_arrives_whole() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let len = 20 << 20;
    assert!(len > 16 << 20 && len <= MAX_FRAME_BYTES);
    let server = tokio::spawn(async move {
        let (tcp, _) = listener.accept().await.unwrap();
        let mut ws = tokio_tungstenite::accept_async(tcp).await.unwrap();
        let body: Vec<u8> = (0..len).map(|i| (i % 251) as u8).collect();
        ws.send(Message::Binary(body.into())).await.unwrap();
        let _ = ws.close(None).await;
    });
    let (mut ws, _) = tokio::time::timeout(
        Duration::from_secs(20),
        tokio_tungstenite::connect_async_with_config(
            format!("ws://{addr}/"),
            Some(ws_config()),
            false,
        ),
    )
    .await
    .expect("connects in time")
    .unwrap();
    let msg = tokio::time::timeout(Duration::from_secs(60), ws.next())
        .await
        .expect("the message arrives in time")
        .expect("a message")
        .expect("not refused as too large");
    let data = msg.into_data();
    assert_eq!(data.len(), len);
    assert!(data.iter().enumerate().all(|(i, &b)| b == (i % 251) as u8));
    server.await.unwrap();
}
