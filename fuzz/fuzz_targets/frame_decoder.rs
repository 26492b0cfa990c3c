//! Arbitrary bytes into the control-frame decoder (in pieces whose sizes the input chooses) and
//! into the treelet-message decoder: nothing may panic, the decoder may never buffer more than
//! its capacity, and it may never stall with a full buffer.
#![no_main]

use arbor_proto::frame::{
    FrameDecoder, check_treelet_message, decode_treelet_message, encode, parse,
};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // The first byte picks the piece size and the decoder's limit; the rest is the stream.
    let Some((&knob, stream)) = data.split_first() else {
        return;
    };
    let piece = usize::from(knob & 0x3f) + 1;
    let mut decoder = if knob & 0x40 == 0 {
        FrameDecoder::for_server()
    } else {
        FrameDecoder::new(usize::from(knob))
    };
    'feed: for chunk in stream.chunks(piece) {
        let mut chunk = chunk;
        while !chunk.is_empty() {
            let taken = decoder.push(chunk);
            assert!(decoder.buffered() <= decoder.capacity());
            chunk = &chunk[taken..];
            let mut progressed = taken > 0;
            loop {
                match decoder.next() {
                    Ok(Some(frame)) => {
                        progressed = true;
                        let bytes = encode(&frame).expect("a decoded frame re-encodes");
                        assert_eq!(parse(&bytes).expect("and decodes again"), frame);
                    }
                    Ok(None) => break,
                    Err(_) => break 'feed,
                }
            }
            assert!(progressed, "decoder stalled");
        }
    }

    let _ = check_treelet_message(stream);
    if let Ok(message) = decode_treelet_message(stream) {
        let blocks =
            message.nodes.len() + message.channels.iter().map(|c| c.1.len()).sum::<usize>();
        assert!(blocks < stream.len());
    }
});
